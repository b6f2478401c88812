"""docs/SCALING.md's tables: env steps/s at 1-256 rollout actors predicted from each stage's measured capacity
(docs/results/scaling.json, written by benchmarks/scaling.py), with the first bottleneck at each scale.

    .venv/bin/python experiments/scaling_model.py

Every stage is a cap on env steps/s; the path runs at the lowest (the driver holds the replay ratio, so a slow
learner slows sampling instead of falling behind):
- rollout actors: N x one actor's env steps/s (one core each);
- replay shards: s / (seconds to insert one env step + seconds to sample its replay_ratio x batch records);
- learners: updates/s / replay_ratio, where one of k data-parallel learners updates on batch/k records (its time
  fitted as fixed + per-record from the two batches measured) and then all-reduces its gradients (a ring:
  2 (k-1)/k x the weights' bytes over the network);
- the driver: 1,000 / its largest CPU seconds per 1,000 env steps (one core: its cost per env step, measured flat
  over 1-8 actors, held at its worst);
- the network: the learner node takes in replay_ratio x batch sampled records per env step; every node pulls the
  weights every weights_every_updates updates.
ASSUMED (not measured): CPU nodes of 16 cores with a 10 Gb/s network (1.25 GB/s each way), 15 of the cores for
rollout actors, replay shards and CPU learners, one each (a core for the node's other processes); a GPU node has one
GPU and holds one learner and nothing else (cluster/ gives Ray none of its CPUs), its update time the one measured
on the GPU named in the results file."""

from __future__ import annotations

import json
import math

from _common import RESULTS, parser

NETWORK = 1.25e9  # bytes/s each way per node: 10 Gb/s, assumed
CORES_PER_NODE = 15
SCALES = (1, 4, 16, 64, 256)
LEARNERS = (1, 2, 4, 8, 16, 32, 64, 128)


class Model:
    def __init__(self, figures: dict):
        actor, shard, learner = figures["rollout_actor"]["reward_only"], figures["replay_shard"], figures["learner_cpu"]
        self.actor = actor["env_steps_per_s"]
        self.batch, self.ratio = learner["batch_size"], learner["replay_ratio"]
        self.samples = self.ratio * self.batch  # replay records sampled per env step: the recipe's, kept at any batch
        self.shard_seconds = 1 / shard["insert_env_steps_per_s"]
        self.record_seconds = 1 / shard["sample_records_per_s"]
        self.record_bytes, self.push_bytes = shard["bytes_per_sampled_record"], actor["bytes_per_env_step"]
        self.weights, self.weights_every = learner["weights_bytes"], learner["weights_every_updates"]
        full, half = 1 / learner["updates_per_s"], 1 / learner["updates_per_s_half_batch"]
        per_record = max(full - half, 0.0) / (self.batch / 2)
        self.cpu_update = lambda b: max(half - per_record * self.batch / 2, 0.0) + per_record * b
        gpu = sorted((int(b), ms / 1000) for b, ms in figures["learner_gpu"]["ms_per_update"].items())
        self.gpu_update = lambda b: interpolate(gpu, b)
        self.driver = 1000 / max(d["cpu_s_per_1000_env_steps"] for d in figures["driver"])

    def caps(self, actors: int, shards: int, learners: int, batch: int, gpu: bool) -> dict[str, float]:
        """Env steps/s each stage allows at ``batch`` records per update (replay_ratio keeps the recipe's samples
        per env step)."""
        ratio = self.samples / batch
        update = (self.gpu_update if gpu else self.cpu_update)(batch / learners)
        allreduce = 2 * (learners - 1) / learners * self.weights / NETWORK
        nodes = sum(nodes_for(actors, shards, learners, gpu))
        return {"rollout actors": actors * self.actor,
                "replay shards": shards / (self.shard_seconds + self.samples * self.record_seconds),
                "learners": 1 / (update + allreduce) / ratio,
                "driver": self.driver,
                "learner network": learners * NETWORK / (self.samples * self.record_bytes),
                "weights broadcast": NETWORK / (nodes * self.weights * ratio / self.weights_every)}

    def best(self, actors: int, gpu: bool, batch: int | None = None) -> dict:
        """The fewest learners and shards that reach the highest rate at ``actors`` (within 2%); ``batch``: fixed
        (each of k learners takes batch / k records, at least 8), or None: the recipe's grown with the learners."""
        options = []
        for k in (k for k in LEARNERS if k <= actors and (batch is None or batch // k >= 8)):
            b = batch or self.batch * k
            for s in sorted({k, *range(k, min(actors, 64) + 1, k)}):
                caps = self.caps(actors, s, k, b, gpu)
                options.append((min(caps.values()), -k, -s, k, s, b, caps))
        rate = max(o[0] for o in options)
        _, _, _, k, s, b, caps = max(o for o in options if o[0] >= 0.98 * rate)  # within 2%: the fewest
        return {"actors": actors, "learners": k, "shards": s, "batch": b, "rate": min(caps.values()),
                "bottleneck": min(caps, key=caps.get)}


def nodes_for(actors: int, shards: int, learners: int, gpu: bool) -> tuple[int, int]:
    """CPU nodes and GPU nodes that hold the actors, shards and learners."""
    cores = actors + shards + (0 if gpu else learners)
    return math.ceil(cores / CORES_PER_NODE), learners if gpu else 0


def interpolate(points: list[tuple[int, float]], x: float) -> float:
    (x0, y0), (x1, y1) = points[0], points[-1]
    for (a, ya), (b, yb) in zip(points, points[1:]):
        if a <= x <= b:
            (x0, y0), (x1, y1) = (a, ya), (b, yb)
            break
    else:
        if x < points[0][0]:
            return points[0][1]
    return y0 + (y1 - y0) * (x - x0) / (x1 - x0)


def stages(figures: dict) -> list[str]:
    actor, teacher = figures["rollout_actor"]["reward_only"], figures["rollout_actor"]["teacher"]
    shard, learner = figures["replay_shard"], figures["learner_cpu"]
    b = learner["batch_size"]
    return ["| stage, alone on one core | measured |", "|---|---:|",
            f"| rollout actor, {actor['config']} | {actor['env_steps_per_s']:,.0f} env steps/s |",
            f"| rollout actor with the teacher, {teacher['config']} | {teacher['env_steps_per_s']:,.0f} env steps/s |",
            f"| replay shard, inserting | {shard['insert_env_steps_per_s']:,.0f} env steps/s |",
            f"| replay shard, sampling batches of {b} | {shard['sample_records_per_s']:,.0f} records/s |",
            f"| learner (CPU), batch {b} / {b // 2} | {learner['updates_per_s']:.1f} / "
            f"{learner['updates_per_s_half_batch']:.1f} updates/s |",
            f"| learner ({figures['learner_gpu']['device']}), batch 32 / 512 | "
            f"{1000 / figures['learner_gpu']['ms_per_update']['32']:.1f} / "
            f"{1000 / figures['learner_gpu']['ms_per_update']['512']:.1f} updates/s |",
            f"| wire: rollout actor -> shard | {actor['bytes_per_env_step']:,.0f} bytes per env step |",
            f"| wire: shard -> learner | {shard['bytes_per_sampled_record']:,.0f} bytes per sampled record |",
            f"| wire: weights to every node, every {learner['weights_every_updates']} updates | "
            f"{learner['weights_bytes'] / 1e6:.1f} MB |"]


def driver(figures: dict) -> list[str]:
    cores = figures["machine"]["cores"]
    rows = [f"| rollout actors | driver CPU seconds per 1,000 env steps | env steps/s (actors sharing {cores} cores) |",
            "|---:|---:|---:|"]
    rows += [f"| {d['actors']} | {d['cpu_s_per_1000_env_steps']:.3f} | {d['env_steps_per_s']:,.0f} |"
             for d in figures["driver"]]
    return rows


def table(model: Model, gpu: bool, grow: bool) -> list[str]:
    rows = ["| rollout actors | nodes (CPU + GPU) | busy actors | learners | replay shards | batch | replay ratio | "
            "env steps/s | first bottleneck |", "|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for n in SCALES:
        r = model.best(n, gpu, None if grow else model.batch)
        cpu, gpus = nodes_for(n, r["shards"], r["learners"], gpu)
        rows.append(f"| {n} | {cpu} + {gpus} | {min(n, math.ceil(r['rate'] / model.actor))} | "
                    f"{r['learners']} | {r['shards']} | {r['batch']} | 1/{r['batch'] / model.samples:g} | "
                    f"{r['rate']:,.0f} | {r['bottleneck']} |")
    return rows


def configs(model: Model) -> list[str]:
    """The resources to ask for on 10 and 100 nodes: g GPU nodes of one learner each, the rest CPU nodes with the
    rollout actors and replay shards, the batch grown with the learners; the fewest GPU nodes within 2% of the
    best rate."""
    out = []
    for nodes in (10, 100):
        options = []
        for g in range(1, nodes):
            room = CORES_PER_NODE * (nodes - g)  # cores of the CPU nodes for actors and shards
            for s in (s for s in (g, 2 * g) if 2 * s <= room):
                caps = model.caps(room - s, s, g, model.batch * g, gpu=True)
                options.append((min(caps.values()), g, s, caps))
        best = max(o[0] for o in options)
        rate, g, s, caps = min((o for o in options if o[0] >= 0.98 * best), key=lambda o: (o[1], o[2]))
        actors = max(math.ceil(rate / model.actor), s)
        cpu, _ = nodes_for(actors, s, g, gpu=True)
        out += [f"On {nodes} nodes: {g} GPU nodes of one learner each and {cpu} CPU node(s) of {actors} rollout "
                f"actors and {s} replay shards, {rate:,.0f} env steps/s, bound by the {min(caps, key=caps.get)}"
                + ("" if cpu + g == nodes else f"; the other {nodes - cpu - g} nodes would add nothing") + ".",
                "", "```yaml", "resources:", f"  num_rollout_actors: {actors}", f"  num_learners: {g}",
                "  num_gpus_per_learner: 1", f"  num_replay_shards: {s}", "train:",
                f"  batch_size: {model.batch * g}", f"  replay_ratio: {model.samples / (model.batch * g):.6g}",
                "```", ""]
    return out


def learners_table() -> list[str]:
    """One learner against two at equal samples (docs/results/learners.json: learners_at_equal_samples.py)."""
    runs = json.loads((RESULTS / "learners.json").read_text())["runs"]
    seeds = sorted({r["seed"] for r in runs})
    rows = ["| learners | " + " | ".join(f"seed {s}" for s in seeds) + " | mean |",
            "|---:|" + "---:|" * (len(seeds) + 1)]
    for k in sorted({r["learners"] for r in runs}):
        rates = {r["seed"]: r["success"] for r in runs if r["learners"] == k}
        rows.append(f"| {k} | " + " | ".join(f"{rates[s]:.1%}" for s in seeds)
                    + f" | {sum(rates.values()) / len(rates):.1%} |")
    return rows


def main() -> None:
    parser(__doc__).parse_args()
    figures = json.loads((RESULTS / "scaling.json").read_text())
    model = Model(figures)
    m, gpu = figures["machine"], figures["learner_gpu"]
    print(f"Measured on {m['cpu']} ({m['cores']} cores, torch {m['torch']}); the GPU learner on {gpu['device']} "
          f"({gpu['measured']}, {gpu['by']}).\n")
    print("\n".join(stages(figures)) + "\n")
    print("\n".join(driver(figures)) + "\n")
    for gpu in (False, True):
        kind = f"GPU learners ({figures['learner_gpu']['device']})" if gpu else "CPU learners"
        print(f"### {kind}, the recipe's batch\n")
        print("\n".join(table(model, gpu, grow=False)) + "\n")
        print(f"### {kind}, the batch grown with the learners\n")
        print("\n".join(table(model, gpu, grow=True)) + "\n")
    print("\n".join(configs(model)))
    print("\n".join(learners_table()) + "\n")


if __name__ == "__main__":
    main()
