"""Held-out accuracy of the learned success classifier on simulated real frames.

    python -m benchmarks.evaluate_success [--episodes 24] [--noise 0.5] [--splits 5] [--keep DIR]

Records ``--episodes`` scripted ``transfer_cube`` episodes with policy noise (the
simulator judges success), writes them as a LeRobot dataset with the builder's ingest
stage, then trains :func:`imac_model.evaluate.success.train_success_classifier` on
``--splits`` different stratified train / held-out splits (seeds 0..) and reports the
held-out accuracy, balanced accuracy and the majority-class baseline of each, with
wall and CPU seconds and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SVT_LOG", "1")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=24)
    ap.add_argument("--noise", type=float, default=0.5)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--splits", type=int, default=5)
    ap.add_argument("--keep", default=None, help="keep the recorded episodes and dataset here")
    args = ap.parse_args(argv)

    from imac_data.build.from_episodes import ingest_episodes
    from imac_data.core.cameras import load_calibration
    from imac_data.core.rig import Rig
    from imac_data.core.robot import aloha
    from imac_data.core.robot.model import RobotModel
    from imac_data.dataset.ingest import IngestOptions
    from imac_data.sources.sim.recorder import SimConfig, record_dataset
    from imac_model.evaluate.success import (
        SuccessClassifierConfig,
        dataset_success_labels,
        image_cameras,
        train_success_classifier,
    )

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="imac_success_"))
    print(f"load average at start: {os.getloadavg()}", flush=True)
    src, root = work / "episodes", work / "dataset"
    t, c = time.perf_counter(), time.process_time()
    if not (src / "calibration.json").is_file():
        record_dataset(SimConfig(num_episodes=args.episodes, width=args.width, height=args.height,
                                 noise=args.noise, seed=0, with_depth=False), src, progress=True)
    if not root.exists():
        ingest_episodes(sorted(src.glob("episode_*.hdf5")), rig=Rig(RobotModel(aloha.robot_config()), load_calibration(src / "calibration.json")),
                        repo_id="local/success_bench", root=root,
                        options=IngestOptions(fps=25, task="transfer the cube", source="policy"), progress=True)
    from imac_data import lerobot_compat as lr

    dataset = lr.LeRobotDataset("local/success_bench", root=root)
    labels = dataset_success_labels(dataset)
    print(f"data: {len(labels)} episodes, {sum(v is True for v in labels.values())} successes; "
          f"{time.perf_counter() - t:.1f} s wall, {time.process_time() - c:.1f} s CPU", flush=True)
    base = SuccessClassifierConfig(cameras=tuple(image_cameras(dataset)))
    rows = []
    for seed in range(args.splits):
        t, c = time.perf_counter(), time.process_time()
        _, report = train_success_classifier(dataset, replace(base, seed=seed))
        h = report["heldout"]
        rows.append({"seed": seed, "heldout_n": h["n"], "heldout_accuracy": h["accuracy"],
                     "heldout_balanced_accuracy": h["balanced_accuracy"], "majority_baseline": h["majority_baseline"],
                     "train_accuracy": report["train"]["accuracy"],
                     "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c})
        print(json.dumps(rows[-1]), flush=True)
    mean = lambda k: sum(r[k] for r in rows) / len(rows)  # noqa: E731
    print(f"mean held-out accuracy {mean('heldout_accuracy'):.3f}, balanced {mean('heldout_balanced_accuracy'):.3f}, "
          f"majority baseline {mean('majority_baseline'):.3f}, train {mean('train_accuracy'):.3f}; "
          f"train+eval {mean('wall_s'):.1f} s wall / {mean('cpu_s'):.1f} s CPU per split; "
          f"load average at end: {os.getloadavg()}")
    print(f"episodes and dataset in {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
