"""Training-time rollout on the CPU: what the online control rebuild and a rollout step cost.

    python -m benchmarks.model_rollout [--quick] [--json PATH]

Workload: one simulated cube-transfer episode (``imac_data.sources.sim.recorder``, noise 0.5, 96x128 per
view, recorded depth), the ALOHA rig of ``recipes/aloha_sim_transfer_cube.yaml``, and the
model of ``imac_model/configs/experiment.yaml`` (the small DiT, 48x64 per view, batch 4,
chunks of 1 + 8 frames, one torch thread as the experiment trains).

* **Online controls** (:meth:`imac_model.pipelines.online_controls.OnlineControls.controls`): motion and
  both contact images of B = 4 chunks from recorded reference frames (their colour depth
  decoded), at the model's view size (``rollout.resolution: model``) and at the dataset's
  (``dataset``). CPU and wall seconds per chunk, median of the timed repeats.
* **Training steps**: an ordinary step (one chunk batch: forward, loss, backward, AdamW) and a
  rollout step with R = 4 (:func:`imac_model.pipelines.rollout.rollout_loss`, backward per chunk, the
  contact images of chunks 2-4 rebuilt from the one-step estimates). The model is randomly
  initialised: its decoded depth is mostly invalid, so the contact rebuild is cheaper than a
  trained model's; the online-controls figure above (recorded depth) is the realistic one.

CPU seconds are the process's (the contact queries' threads included); the machine may be
shared, so the load average is recorded at start and end. No figure is asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.small_world import CHUNK, DATASET_HW, MODEL_HW, VIEWS, experiment_spec, one_thread, recorded_mosaics

B, R = 4, 4


def _timed(fn, repeats: int):
    walls, cpus = [], []
    for _ in range(repeats + 1):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls[1:]), statistics.median(cpus[1:])  # the first call builds caches


def run(quick: bool = False) -> dict:
    import torch

    from imac_data.core.depth import DepthCodec
    from imac_data.core.rig import Rig
    from imac_data.recipes import RECIPES_DIR, load_recipe
    from imac_data.sources.hdf5 import read_episode
    from imac_data.sources.sim.recorder import SimConfig, record_dataset
    from imac_model.data.batch import ChunkBatch
    from imac_model.models.world_model import WorldModel
    from imac_model.pipelines.online_controls import OnlineControls
    from imac_model.pipelines.rollout import rollout_loss

    one_thread()
    load_start = os.getloadavg()
    views, H, hw, model_hw = VIEWS, CHUNK, DATASET_HW, MODEL_HW
    repeats = 1 if quick else 3
    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        record_dataset(SimConfig(num_episodes=1, width=hw[1], height=hw[0], noise=0.5,
                                 max_steps=2 * (R * H + 2) * (2 if quick else 3)), sim, progress=False)
        ep = read_episode(sim / "episode_0.hdf5")
        rig = Rig.from_recipe(load_recipe(RECIPES_DIR / "aloha_sim_transfer_cube.yaml"), sim / "calibration.json")
    codec = DepthCodec.preset("manipulation")
    spec = experiment_spec()

    def frames(idx, size):  # recorded mosaics (B, n, 3, 2h, 3w) at ``size``
        return recorded_mosaics(ep, codec, idx, size)

    starts = [c * H for c in range(B)]  # B chunks, each a clip of R chunks
    result: dict = {"rollout_batch": B, "rollout_chunks": R, "rollout_view_hw": list(model_hw),
                    "rollout_dataset_hw": list(hw), "rollout_quick": quick}
    q_ref = torch.as_tensor(ep.qpos[starts], dtype=torch.float32)
    actions = torch.stack([torch.as_tensor(ep.action[s:s + H], dtype=torch.float32) for s in starts])
    reference = torch.stack([frames([s], model_hw)[0] for s in starts])
    for resolution in ("model", "dataset"):
        online = OnlineControls(rig, codec, views, model_hw, hw, resolution=resolution)
        wall, cpu = _timed(lambda: online.controls(reference, q_ref, actions), repeats)
        result[f"online_controls_cpu_s_per_chunk_{resolution}"] = cpu / B
        result[f"online_controls_wall_s_per_chunk_{resolution}"] = wall / B

    online = OnlineControls(rig, codec, views, model_hw, hw)
    torch.manual_seed(0)
    model = WorldModel(spec)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    clip = []
    for r in range(R):
        s = [x + r * H for x in starts]
        ctl = online.controls(torch.stack([frames([x], model_hw)[0] for x in s]),
                              torch.as_tensor(ep.qpos[s], dtype=torch.float32),
                              torch.stack([torch.as_tensor(ep.action[x:x + H], dtype=torch.float32) for x in s]))
        clip.append(ChunkBatch(reference=torch.stack([frames([x], model_hw)[0] for x in s]),
                               actions=torch.stack([torch.as_tensor(ep.action[x:x + H], dtype=torch.float32)
                                                    for x in s]),
                               controls=ctl.controls,
                               future=torch.stack([frames(list(range(x + 1, x + H + 1)), model_hw) for x in s]),
                               state=torch.as_tensor(ep.qpos[s], dtype=torch.float32)))

    def ordinary():
        out = model(clip[0], generator=torch.Generator().manual_seed(0))
        out.loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    def rollout():
        rollout_loss(model, clip, online, generator=torch.Generator().manual_seed(0),
                     backward=lambda loss: loss.backward())
        opt.step()
        opt.zero_grad(set_to_none=True)

    for name, fn in (("ordinary", ordinary), ("rollout", rollout)):
        wall, cpu = _timed(fn, repeats)
        result[f"train_step_cpu_s_{name}"] = cpu
        result[f"train_step_wall_s_{name}"] = wall
    result["rollout_step_cpu_ratio"] = result["train_step_cpu_s_rollout"] / result["train_step_cpu_s_ordinary"]
    result["load_average_start_end"] = [round(x, 2) for x in load_start + os.getloadavg()]
    return result


def report(r: dict) -> str:
    return "\n".join([
        f"Training-time rollout on the CPU (batch {r['rollout_batch']}, R = {r['rollout_chunks']}, model "
        f"{r['rollout_view_hw'][0]}x{r['rollout_view_hw'][1]} per view, one torch thread; load average "
        f"{r['load_average_start_end']})",
        "| workload | CPU s | wall s |", "|---|---|---|",
        f"| online controls per chunk, at the model's size | {r['online_controls_cpu_s_per_chunk_model']:.3f} | "
        f"{r['online_controls_wall_s_per_chunk_model']:.3f} |",
        f"| online controls per chunk, at the dataset's size ({r['rollout_dataset_hw'][0]}x"
        f"{r['rollout_dataset_hw'][1]}) | {r['online_controls_cpu_s_per_chunk_dataset']:.3f} | "
        f"{r['online_controls_wall_s_per_chunk_dataset']:.3f} |",
        f"| ordinary training step | {r['train_step_cpu_s_ordinary']:.2f} | {r['train_step_wall_s_ordinary']:.2f} |",
        f"| rollout training step (R = {r['rollout_chunks']}) | {r['train_step_cpu_s_rollout']:.2f} | "
        f"{r['train_step_wall_s_rollout']:.2f} |",
    ])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.model_rollout", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="one timed repeat")
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    r = run(quick=args.quick)
    print(report(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    return r


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main()
