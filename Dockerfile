# formation on the official Ray image of the Ray version we pin (pyproject.toml).
#   docker build -t formation:cpu .
#   docker build --build-arg VARIANT=gpu -t formation:gpu .
#   docker run --rm formation:cpu formation evaluate policies/setting1 --episodes 100
# Clusters use them as cluster/README.md shows (push them to your registry first).
ARG RAY_VERSION=2.60.0
ARG VARIANT=cpu
FROM rayproject/ray:${RAY_VERSION}-py311-${VARIANT}
ARG VARIANT
ARG TORCH_VERSION=2.13.0

# torch is not in the Ray image: the CPU build for the cpu variant (a few hundred MB), the CUDA
# build from PyPI for the gpu variant. The pinned torch wheel brings its own CUDA runtime (the nvidia-* wheels
# it pins), so the CUDA the learner runs on is fixed by TORCH_VERSION; a GPU node needs only a driver for it.
RUN if [ "$VARIANT" = "cpu" ]; then \
        pip install --no-cache-dir "torch==${TORCH_VERSION}" --index-url https://download.pytorch.org/whl/cpu; \
    else \
        pip install --no-cache-dir "torch==${TORCH_VERSION}"; \
    fi

WORKDIR /home/ray/formation
COPY --chown=ray:users pyproject.toml README.md ./
COPY --chown=ray:users formation ./formation
COPY --chown=ray:users configs ./configs
COPY --chown=ray:users policies ./policies
# the package and what it adds to the image (Ray and numpy are there already); `formation` goes on the PATH
RUN pip install --no-cache-dir . && formation --help > /dev/null
