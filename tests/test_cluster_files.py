"""The container and cluster files name only images, commands and configs that exist here.

No Docker engine or Kubernetes runs on this machine: the Dockerfile, the KubeRay RayJob and the
cluster launcher YAML are checked against the repo, our CLI's parser and config loader, and Ray's
own cluster-config schema."""

import re
import shlex
from pathlib import Path

import yaml

from formation.cli import build_parser, parse_overrides
from formation.recipe.config import RunConfig
from formation.storage import is_uri

REPO = Path(__file__).resolve().parent.parent
IMAGE_DIR = "/home/ray/formation"  # the Dockerfile's WORKDIR


def pinned_ray_version() -> str:
    return re.search(r'"ray\[[\w,]+\]==([\d.]+)"', (REPO / "pyproject.toml").read_text()).group(1)


def dockerfile_images() -> set[str]:
    """The tags the Dockerfile's header tells users to build."""
    return set(re.findall(r"docker build .*-t (\S+) \.", (REPO / "Dockerfile").read_text()))


def check_train_command(command: str) -> RunConfig | None:
    """A `formation train` command line: our parser accepts it, its config exists in the repo (under the
    image's WORKDIR) and loads with its --set overrides, and --out is a storage URI. Returns that
    config (None for a --resume, which reads the run's own)."""
    words = shlex.split(command)
    assert words[0] == "formation"
    args = build_parser().parse_args(words[1:])
    assert args.command == "train"
    assert is_uri(args.out), "a cluster run writes to storage that outlives it"
    if args.resume:  # the run's own config.yaml, at --out
        assert args.config is None
        return None
    config = Path(args.config)
    if config.is_absolute():
        assert str(config).startswith(IMAGE_DIR + "/"), config
        config = Path(str(config)[len(IMAGE_DIR) + 1:])
    assert (REPO / config).is_file(), f"{config} is not in the repo"
    return RunConfig.load(REPO / config, parse_overrides(args.set))


def test_the_dockerfile_builds_on_the_pinned_ray_image_and_copies_what_exists():
    text = (REPO / "Dockerfile").read_text()
    assert f"ARG RAY_VERSION={pinned_ray_version()}" in text
    assert "FROM rayproject/ray:${RAY_VERSION}-py311-${VARIANT}" in text
    assert dockerfile_images() == {"formation:cpu", "formation:gpu"}
    for source in re.findall(r"^COPY (?:--\S+ )*(.+) \S+$", text, flags=re.M):
        for name in source.split():
            assert (REPO / name).exists(), f"the Dockerfile copies {name}, which is not in the repo"
    assert "pip install --no-cache-dir ." in text  # the package, so `formation` is on the PATH
    # torch, and with it the gpu image's CUDA runtime, is the version the Makefile pins
    makefile = (REPO / "Makefile").read_text()
    assert re.search(r"^ARG TORCH_VERSION=(\S+)$", text, re.M).group(1) == \
        re.search(r"^TORCH \?= torch==(\S+)$", makefile, re.M).group(1)


def test_the_rayjob_runs_formation_train_on_a_gpu_learner_and_cpu_rollout_workers():
    job = yaml.safe_load((REPO / "cluster" / "rayjob.yaml").read_text())
    assert (job["apiVersion"], job["kind"]) == ("ray.io/v1", "RayJob")
    spec = job["spec"]
    run = check_train_command(spec["entrypoint"])
    cluster = spec["rayClusterSpec"]
    assert cluster["rayVersion"] == pinned_ray_version()
    pods = [("head", cluster["headGroupSpec"]["template"])]
    pods += [(g["groupName"], g["template"]) for g in cluster["workerGroupSpecs"]]
    # KubeRay (v1.5.1 or newer) sets the token of this secret (key auth_token) on every Ray container; the
    # submitter reads the same one
    assert cluster["authOptions"] == {"mode": "token", "secretName": "formation-ray-token"}
    submitter = {e["name"]: e for e in spec["submitterPodTemplate"]["spec"]["containers"][0]["env"]}
    assert submitter["RAY_AUTH_MODE"]["value"] == "token"
    assert submitter["RAY_AUTH_TOKEN"]["valueFrom"]["secretKeyRef"] == {"name": "formation-ray-token",
                                                                       "key": "auth_token"}
    assert "auth_token=" in (REPO / "cluster" / "rayjob.yaml").read_text()  # how its header makes the secret
    pods.append(("submitter", spec["submitterPodTemplate"]))
    gpus = {}
    for name, template in pods:
        for container in template["spec"]["containers"]:
            assert container["image"] in dockerfile_images(), (name, container["image"])
            limits = container.get("resources", {}).get("limits", {})
            gpus[name] = int(limits.get("nvidia.com/gpu", 0))
    assert gpus["gpu-learner"] == 1 and gpus["cpu-rollout"] == 0
    gpu_image = cluster["workerGroupSpecs"][0]["template"]["spec"]["containers"][0]["image"]
    assert gpu_image == "formation:gpu"
    # the GPU pod offers Ray no CPUs: the rollout actors stay off it, the GPU learner (which asks no CPU) goes there
    assert cluster["workerGroupSpecs"][0]["rayStartParams"] == {"num-cpus": "0"}
    # what the entrypoint asks for fits the CPU worker groups (else the run fails fast on the cluster)
    cpus = sum(int(g["replicas"]) * int(g["template"]["spec"]["containers"][0]["resources"]["limits"]["cpu"])
               for g in cluster["workerGroupSpecs"] if g["rayStartParams"].get("num-cpus") != "0")
    assert run.resources.num_rollout_actors * run.resources.cpus_per_rollout_actor <= cpus
    assert run.resources.num_gpus_per_learner <= sum(gpus.values())


def test_the_launcher_yaml_passes_rays_schema_and_uses_our_images():
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = yaml.safe_load((REPO / "cluster" / "launcher.yaml").read_text())
    validate_config(prepare_config(config))  # Ray's own ray-schema.json, with its AWS defaults filled in
    images = {config["docker"]["image"], config["docker"]["worker_image"]}
    images |= {t["docker"]["worker_image"] for t in config["available_node_types"].values() if "docker" in t}
    assert images == dockerfile_images()
    assert config["available_node_types"]["gpu_learner"]["docker"]["worker_image"] == "formation:gpu"
    assert config["available_node_types"]["gpu_learner"]["resources"] == {"CPU": 0, "GPU": 1}  # no rollout actors
    # the machine image is pinned: Ray 2.60's own default for the region (read from its source: importing that
    # module needs boto3)
    import ray.autoscaler

    source = (Path(ray.autoscaler.__file__).parent / "_private" / "aws" / "config.py").read_text()
    region = config["provider"]["region"]
    default = re.search(rf'"{region}": "(ami-[0-9a-f]+)"', source).group(1)
    for node_type in config["available_node_types"].values():
        assert node_type["node_config"]["ImageId"] == default
    # `ray start` turns token authentication on only where it finds a token: every node starts with it on, and
    # gets the token made beforehand on the user's machine
    for command in config["head_start_ray_commands"] + config["worker_start_ray_commands"]:
        if "ray start" in command:
            assert "RAY_AUTH_MODE=token ray start" in command, command
    assert config["file_mounts"] == {"~/.ray/auth_token": "~/.ray/auth_token"}


def test_the_cluster_readme_commands_use_files_and_configs_that_exist():
    text = (REPO / "cluster" / "README.md").read_text()
    blocks = [chunk.split("```")[0] for chunk in text.split("```bash")[1:]]
    commands = [line.strip() for b in blocks for line in b.replace("\\\n", " ").splitlines()]
    trains = [c for c in commands if c.startswith("formation train") or " -- formation train" in c]
    assert trains, "the walk-through submits a training"
    for command in trains:
        check_train_command(command[command.index("formation train"):])
    assert any("--resume" in c for c in trains), "the walk-through shows how to continue a run"
    for path in re.findall(r"\b((?:cluster|configs)/[\w./-]+\.ya?ml)\b", text):
        assert (REPO / path).is_file(), f"cluster/README.md names {path}, which is not in the repo"
