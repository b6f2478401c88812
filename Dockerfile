# formation on the official Ray image of the Ray version we pin.
#   docker build -t formation:cpu .
#   docker build --build-arg VARIANT=gpu -t formation:gpu .
#   docker run --rm formation:cpu formation show --out /tmp/show
ARG RAY_VERSION=2.60.0
ARG VARIANT=cpu
FROM rayproject/ray:${RAY_VERSION}-py311-${VARIANT}

WORKDIR /home/ray/formation
COPY --chown=ray:users pyproject.toml README.md ./
COPY --chown=ray:users formation ./formation
COPY --chown=ray:users configs ./configs
# Ray, torch and numpy come with the image; install the package and what it adds.
RUN pip install --no-cache-dir .
