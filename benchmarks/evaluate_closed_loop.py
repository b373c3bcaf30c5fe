"""Closed-loop evaluation on the CPU: what one world-model chunk of a closed loop costs.

    python -m benchmarks.evaluate_closed_loop [--quick] [--json PATH]

Workload: one simulated cube-transfer episode (``imac_data.sources.sim.recorder``, noise 0.5, 96x128 per
view, recorded depth) as the start, the ALOHA rig of ``recipes/aloha_sim_transfer_cube.yaml``, the
model of ``imac_model/configs/experiment.yaml`` (the small DiT, 48x64 per view, chunks of 1 + 8
frames, ``motion+contact``, one torch thread), randomly initialised with its zero-initialised
layers randomised (an untrained model's generated depth is mostly invalid, so the contact rebuild
of chunks after the first is cheaper than a trained model's).

Per chunk (:func:`imac_model.evaluate.closed_loop.rollout_episode` over ``CHUNKS`` chunks, the
generated episode written by :class:`~imac_model.evaluate.closed_loop.GeneratedDatasetWriter`):

* **policy**: a tiny LeRobot ACT (random weights, 96x128 input, chunks of 8 actions) through
  :class:`~imac_model.evaluate.policies.LeRobotPolicy` (pre-processor, 8 ``select_action``
  calls, post-processor), and a replay of the recorded actions (no compute);
* **world model**: the online control rebuild (motion and both contact images) plus sampling
  (``sample_steps`` Euler steps), one :func:`imac_model.pipelines.rollout.sample_rollout` call;
* **write**: encoding the chunk's frames (generated RGB and depth, 3 control streams, 3 views)
  with LeRobot's default encoder.

CPU and wall seconds per chunk, median over the chunks after the first (the first builds
caches); the load average is recorded at start and end. No figure is asserted anywhere.
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

CHUNKS = 4


class _Clock:
    def __init__(self):
        self.wall = self.cpu = 0.0

    def __enter__(self):
        self._w, self._c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall += time.perf_counter() - self._w
        self.cpu += time.process_time() - self._c


def _act(directory: Path, hw, stats) -> Path:
    import torch

    from imac_model.evaluate.policies import lerobot_name

    FeatureType, PolicyFeature, ACTConfig, ACTPolicy, make_pre_post_processors = (
        lerobot_name(n) for n in ("FeatureType", "PolicyFeature", "ACTConfig", "ACTPolicy", "make_pre_post_processors"))

    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (14,)),
              "observation.images.cam_high": PolicyFeature(FeatureType.VISUAL, (3, *hw))}
    cfg = ACTConfig(input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (14,))},
                    chunk_size=8, n_action_steps=8, dim_model=64, n_heads=2, dim_feedforward=128,
                    n_encoder_layers=1, n_decoder_layers=1, use_vae=False, pretrained_backbone_weights=None,
                    device="cpu")
    torch.manual_seed(0)
    policy = ACTPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(directory)
    return directory


def run(quick: bool = False) -> dict:
    import torch

    from imac_data.core.depth import DepthCodec
    from imac_data.core.rig import Rig
    from imac_data.recipes import RECIPES_DIR, load_recipe
    from imac_data.sources.hdf5 import read_episode
    from imac_data.sources.sim.recorder import SimConfig, record_dataset
    from imac_model.evaluate.closed_loop import GeneratedDatasetWriter, Start, rollout_episode
    from imac_model.evaluate.policies import ActionQueue, LeRobotPolicy, recorded_actions_policy
    from imac_model.models.world_model import WorldModel
    from imac_model.pipelines.online_controls import OnlineControls

    one_thread()
    load_start = os.getloadavg()
    views, H, hw, model_hw = VIEWS, CHUNK, DATASET_HW, MODEL_HW
    chunks = 2 if quick else CHUNKS
    spec = experiment_spec()
    torch.manual_seed(0)
    model = WorldModel(spec).eval()
    for p in model.parameters():
        if not p.detach().any():
            torch.nn.init.normal_(p, std=0.05)
    codec = DepthCodec.preset("manipulation")
    result: dict = {"closed_loop_chunks": chunks, "closed_loop_chunk_frames": H, "closed_loop_view_hw": list(model_hw),
                    "closed_loop_sample_steps": spec.flow.sample_steps, "closed_loop_quick": quick}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        record_dataset(SimConfig(num_episodes=1, width=hw[1], height=hw[0], noise=0.5, max_steps=chunks * H + 2),
                       tmp / "sim", progress=False)
        ep = read_episode(tmp / "sim" / "episode_0.hdf5")
        rig = Rig.from_recipe(load_recipe(RECIPES_DIR / "aloha_sim_transfer_cube.yaml"), tmp / "sim" / "calibration.json")
        online = OnlineControls(rig, codec, views, model_hw, hw)
        reference = recorded_mosaics(ep, codec, [0])[0]
        actions = torch.as_tensor(ep.action, dtype=torch.float32)
        start = Start(episode=0, frame=0, reference=reference, state=torch.as_tensor(ep.qpos[0], dtype=torch.float32),
                      chunks=chunks, seed=0, task="transfer", recorded_actions=actions)
        stats = {"observation.state": {"mean": actions.mean(0), "std": actions.std(0) + 1e-3},
                 "action": {"mean": actions.mean(0), "std": actions.std(0) + 1e-3},
                 "observation.images.cam_high": {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)}}
        act = LeRobotPolicy.from_pretrained(_act(tmp / "act", hw, stats))
        act.check(views=views, action_dim=14, state_dim=14)
        for name, policy in (("act", act), ("recorded", recorded_actions_policy(actions))):
            clock = _Clock()

            def timed(obs, policy=policy, clock=clock):
                with clock:
                    return policy(obs)

            queue = ActionQueue(timed, 14)
            writer = GeneratedDatasetWriter(tmp / f"out_{name}", f"local/{name}", spec)
            writer.begin_episode(start, {})
            rows = []
            it = rollout_episode(model, online, queue, start)
            for _ in range(chunks):
                before = (clock.wall, clock.cpu)
                total = _Clock()
                with total:
                    record = next(it)
                write = _Clock()
                with write:
                    writer.add_chunk(record)
                policy_wall, policy_cpu = clock.wall - before[0], clock.cpu - before[1]
                rows.append({"policy": (policy_wall, policy_cpu),
                             "world_model": (total.wall - policy_wall, total.cpu - policy_cpu),
                             "write": (write.wall, write.cpu)})
            writer.end_episode()
            writer.abort()  # not needed further
            timed_rows = rows[1:] or rows
            for part in ("policy", "world_model", "write"):
                result[f"{name}_{part}_wall_s_per_chunk"] = statistics.median(r[part][0] for r in timed_rows)
                result[f"{name}_{part}_cpu_s_per_chunk"] = statistics.median(r[part][1] for r in timed_rows)
    result["load_average_start_end"] = [round(x, 2) for x in load_start + os.getloadavg()]
    return result


def report(r: dict) -> str:
    lines = [f"Closed loop on the CPU ({r['closed_loop_chunks']} chunks of {r['closed_loop_chunk_frames']} frames, "
             f"model {r['closed_loop_view_hw'][0]}x{r['closed_loop_view_hw'][1]} per view, "
             f"{r['closed_loop_sample_steps']} Euler steps, one torch thread; load average "
             f"{r['load_average_start_end']})", "| policy | part | CPU s / chunk | wall s / chunk |", "|---|---|---|---|"]
    for name in ("act", "recorded"):
        for part in ("policy", "world_model", "write"):
            lines.append(f"| {name} | {part.replace('_', ' ')} | {r[f'{name}_{part}_cpu_s_per_chunk']:.3f} | "
                         f"{r[f'{name}_{part}_wall_s_per_chunk']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.evaluate_closed_loop", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="two chunks")
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
