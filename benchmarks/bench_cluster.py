"""Does a two-node Ray cluster on one host run the DAG to the outputs of a serial ``dvc repro``?  ``geodistill
run`` on ``ray.cluster_utils.Cluster`` (two nodes of ``--cpus`` CPUs, ``--gpus`` fake GPUs) in a project copy, then
every output hash of the two ``dvc.lock`` files compared (benchmark and report outputs embed time: they differ).

    python -m benchmarks.bench_cluster --repo COPY --serial DONE [--targets teacher ...]
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import yaml

from benchmarks.common import parser
from pipeline.cluster import driver


def lock_outs(repo: Path) -> dict[tuple[str, str], str]:
    """``{(stage, out path): md5}`` of a project's dvc.lock."""
    stages = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]
    return {(s, o["path"]): o.get("md5", "") for s, e in stages.items() for o in e.get("outs", [])}


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--repo", required=True, type=Path)
    ap.add_argument("--serial", required=True, type=Path)
    ap.add_argument("--targets", nargs="*", default=[])
    ap.add_argument("--cpus", type=int, default=1)
    ap.add_argument("--gpus", type=int, default=1)
    args = ap.parse_args(argv)

    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": args.cpus, "num_gpus": args.gpus})
    cluster.add_node(num_cpus=args.cpus, num_gpus=args.gpus)
    ray.init(address=cluster.address, log_to_driver=False, logging_level="WARNING")
    try:
        t = time.time()
        result = driver.run_pipeline(args.repo, tuple(args.targets), echo=print)
        wall = time.time() - t
        nodes = {n: r.get("node_id", "")[:8] for n, r in result.results.items()}
    finally:
        ray.shutdown()
        cluster.shutdown()
    a, b = lock_outs(args.repo), lock_outs(args.serial)
    ran = {k: v for k, v in a.items() if k[0] in result.results}
    differ = sorted(f"{s}:{p}" for (s, p), h in ran.items() if b.get((s, p)) != h)
    print(f"two nodes x {args.cpus} CPU x {args.gpus} fake GPU: {len(result.results)} stages in {wall:.1f} s; "
          f"{len(set(nodes.values()))} nodes used")
    for n, node in nodes.items():
        print(f"  {n:28s} node {node}  {result.results[n]['status']}")
    print(f"outputs equal to the serial dvc repro: {len(ran) - len(differ)} of {len(ran)}; differ: {differ or 'none'}")
    out = {"wall_s": wall, "ok": result.ok, "nodes": nodes, "outputs": len(ran), "differ": differ}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
