"""The CUDA paths of the build's core, on their own: forward kinematics, the robot raster and contact images.

    python -m benchmarks.cuda_paths export DIR            # here: MuJoCo + Open3D make the inputs
    python -m benchmarks.cuda_paths run DIR [--json PATH]  # on the GPU machine: times and checks

A GPU machine without MuJoCo's renderer, Open3D or LeRobot (the ``device`` tool's: Python
3.12, torch, 64 MiB of files per call) cannot run the build, so the work is split:

* ``export`` simulates gym-aloha's ``transfer_cube`` (seed 0, the scripted policy, 25 fps)
  at 240x320 and 480x640, renders the robot with our renderer, and writes what FK and
  :func:`imac_data.core.contact.images.contact_chunk` take: the rig (``rig.json`` + the packaged robot
  description, exactly what a built dataset carries), joint vectors, the recorded depth at
  the chunk references (uint16 millimetres, as recorded), the rendered robot depth, the
  camera poses and the gripper surface points of every frame (``inputs_HxW.npz``).
* ``run`` rebuilds the rig with :meth:`Rig.from_block` and times, on the CPU (``--cpu-threads``
  torch threads / KD-tree workers, and all cores) and on CUDA:

  - FK (:meth:`Rig.link_poses`) and what the renderer and contact take from it besides
    the raster (camera poses, gripper surface points), for batches of 1 to 4096 joint
    vectors; checked against MuJoCo's own body poses at the episode's frames (the
    oracle; the export stores them) and CUDA's float32 against float64 FK on the CPU;
  - contact images of every chunk (8 future steps, 3 views) at both sizes, with the
    default certified tolerance and exact (``tolerance=None``). The oracle is the CPU's
    exact answer (a KD-tree); CUDA computes by brute force (``method="torch"``), a different
    algorithm, so agreement is a check of both: the exact distances must agree to float32
    rounding and the certified ones lie within the tolerance above the exact ones.

  - the robot raster of every frame (3 views) with the torch rasteriser (``imac build --device cuda``'s
    renderer), checked against the export's Open3D ray casting (the CPU build's renderer, another
    algorithm): mask IoU and depth within 1 mm.

The CPU rows run pinned to ``--cpu-threads`` cores and to all
cores. ``--bruteforce-cpu``: without CUDA, the CUDA algorithms (brute-force contact, the rasteriser) run on
the CPU and are checked the same way (the test does this at 120x160). Timings: the first pass over the chunks warms up kernels and
caches and is not counted; CUDA times are wall time between ``torch.cuda.synchronize``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

CHUNK = 8
SIZES = {"240x320": (240, 320, 48), "480x640": (480, 640, 24)}  # name: (H, W, frames)
QUICK_SIZES = {"120x160": (120, 160, 9)}  # the test's
FK_BATCHES = (1, 8, 64, 512, 4096)


# ----------------------------------------------------------------------------- export (CPU, MuJoCo)


def export(out: Path, sizes: dict = SIZES, seed: int = 0) -> None:
    import mujoco

    from imac_data.core.contact.images import chunk_plan
    from imac_data.core.contact.workspace import resolve_workspace, saturation_depth
    from imac_data.core.depth import DepthCodec
    from imac_data.core.rig import Rig
    from imac_data.core.robot.aloha import ARMS, robot_config
    from imac_data.core.robot.description import write_description
    from imac_data.core.robot.model import RobotModel
    from imac_data.sources.sim.env import FrameRenderer
    from imac_data.sources.sim.recorder import simulate_episode
    from imac_data.sources.sim.rig import camera_calibration, load_mujoco_model

    out.mkdir(parents=True, exist_ok=True)
    model = load_mujoco_model("transfer_cube")
    robot = RobotModel(robot_config())
    rig = Rig.from_platform("aloha_sim", camera_calibration(model, 320, 240), robot=robot,
                            workspace=resolve_workspace(None, robot, saturation_depth(DepthCodec.preset("manipulation"))))
    write_description(rig.robot, out / "robot")
    (out / "rig.json").write_text(json.dumps(rig.to_info(), indent=1))
    (out / "sizes.json").write_text(json.dumps(sizes))
    for name, (H, W, T) in sizes.items():
        renderer = FrameRenderer(load_mujoco_model("transfer_cube"), W, H, keep_qpos=True)
        try:
            # frames spread over the grasp: the policy's first ~40 steps barely move
            ep = simulate_episode("transfer_cube", seed=seed, frame_stride=2, max_steps=2 * T + 200,
                                  renderer=renderer)
        finally:
            renderer.close()
        keep = slice(len(ep.qpos) - T, len(ep.qpos))
        q = torch.as_tensor(ep.qpos[keep], dtype=torch.float32)
        views = rig.robot_views(q, resolution=(H, W))
        refs = [r for r, _ in chunk_plan(T, CHUNK)]
        depth_mm = np.stack([ep.depth_mm[n][keep] for n in rig.names], 1)[refs]
        # the oracle for FK: MuJoCo's own body poses at every kept frame
        mj = renderer.model
        bodies = [b for b in range(1, mj.nbody) if mj.body(b).name in rig.robot.link_names]
        xpos, xmat = [], []
        state = mujoco.MjData(mj)
        # the dataset records one finger per arm: MuJoCo's other finger (its own joint in the
        # simulation, held back by the cube while grasping) is set to the URDF's mimic rule
        fingers = [(mj.jnt_qposadr[mj.joint(f"{arm}/left_finger").id],
                    mj.jnt_qposadr[mj.joint(f"{arm}/right_finger").id]) for arm in ARMS]
        for qpos in renderer.qpos[keep]:
            state.qpos[:] = qpos
            for left, right in fingers:
                state.qpos[right] = -qpos[left]
            mujoco.mj_kinematics(mj, state)
            xpos.append(state.xpos[bodies].copy())
            xmat.append(state.xmat[bodies].reshape(-1, 3, 3).copy())
        np.savez_compressed(out / f"inputs_{name}.npz", q=q.numpy(), refs=np.array(refs), ref_depth_mm=depth_mm,
                            robot_depth=views.depth.numpy(), T_world_cam=views.T_world_cam.numpy(),
                            gripper_points=views.gripper_points.numpy(),
                            mujoco_bodies=np.array([mj.body(b).name for b in bodies]),
                            mujoco_xpos=np.array(xpos), mujoco_xmat=np.array(xmat))
        print(f"{name}: {T} frames, {len(refs)} chunks -> {out / f'inputs_{name}.npz'} "
              f"({(out / f'inputs_{name}.npz').stat().st_size / 1e6:.1f} MB)")


# ----------------------------------------------------------------------------- run (CUDA machine)


_START = time.perf_counter()


def _progress(message: str) -> None:
    print(f"[{time.perf_counter() - _START:7.1f} s] {message}", file=sys.stderr, flush=True)


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn, repeats: int) -> float:
    """Best wall seconds of ``repeats`` calls (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        _sync()
        t = time.perf_counter()
        fn()
        _sync()
        best = min(best, time.perf_counter() - t)
    return best


@contextlib.contextmanager
def _cores(n: int | None):
    """Run on the first ``n`` cores with ``n`` torch threads (None: all cores)."""
    old_threads, old_cores = torch.get_num_threads(), os.sched_getaffinity(0)
    n = n or len(old_cores)
    os.sched_setaffinity(0, sorted(old_cores)[:n])
    torch.set_num_threads(n)
    try:
        yield
    finally:
        os.sched_setaffinity(0, old_cores)
        torch.set_num_threads(old_threads)


def _load_rig(inputs: Path):
    from imac_data.core.rig import Rig

    return Rig.from_block(json.loads((inputs / "rig.json").read_text()), inputs / "robot")


def fk_figures(rig, q_episode: torch.Tensor, cpu_threads: int, repeats: int, batches=FK_BATCHES) -> dict:
    """FK, camera poses and gripper points: ms per call on the CPU and on CUDA, per batch."""
    gen = torch.Generator().manual_seed(0)
    out = {}
    for B in batches:
        # episode configurations with a little noise: realistic poses, every entry distinct
        pick = torch.randint(len(q_episode), (B,), generator=gen)
        q = q_episode[pick] + 0.05 * torch.randn(B, q_episode.shape[1], generator=gen)
        exact = rig.link_poses(q.double())

        def fk(qd):
            return rig.link_poses(qd)

        def fk_and_points(qd):
            lp = rig.link_poses(qd)
            return lp, rig.camera_poses(link_poses=lp), rig.gripper.points(lp)

        row = {}
        devices = [("cpu", q, cpu_threads), ("cpu_all", q, None)]
        if torch.cuda.is_available():
            devices.append(("cuda", q.cuda(), None))
        for label, qd, cores in devices:
            _progress(f"FK batch {B} on {label}")
            with _cores(cores):
                row[f"{label}_fk_ms"] = 1e3 * _timed(lambda: fk(qd), repeats)
                row[f"{label}_fk_points_ms"] = 1e3 * _timed(lambda: fk_and_points(qd), repeats)
        if torch.cuda.is_available():
            lp = rig.link_poses(q.cuda())
            row["cuda_max_translation_error_m"] = max(
                float((lp[k][..., :3, 3].double().cpu() - exact[k][..., :3, 3]).abs().max()) for k in exact)
            row["cuda_max_rotation_error"] = max(
                float((lp[k][..., :3, :3].double().cpu() - exact[k][..., :3, :3]).abs().max()) for k in exact)
            cpu32 = rig.link_poses(q)
            row["cpu_float32_max_translation_error_m"] = max(
                float((cpu32[k][..., :3, 3].double() - exact[k][..., :3, 3]).abs().max()) for k in exact)
        out[B] = row
    return out


def fk_vs_mujoco(rig, data) -> dict:
    """Max deviation of our FK from MuJoCo's body poses at the episode's frames (the
    independent oracle), per device and dtype: translation (m) and rotation entries."""
    q = torch.as_tensor(data["q"])
    names = [str(n) for n in data["mujoco_bodies"]]
    want_t, want_r = torch.as_tensor(data["mujoco_xpos"]), torch.as_tensor(data["mujoco_xmat"])
    out = {"frames": len(q), "bodies": len(names)}
    devices = ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    for dev in devices:
        for dtype in (torch.float64, torch.float32):
            poses = rig.link_poses(q.to(dev, dtype))
            got = torch.stack([poses[n].cpu().double() for n in names], 1)  # (T, L, 4, 4)
            tag = f"{dev}_{str(dtype).removeprefix('torch.')}"
            out[f"{tag}_max_translation_error_m"] = float((got[..., :3, 3] - want_t).abs().max())
            out[f"{tag}_max_rotation_error"] = float((got[..., :3, :3] - want_r).abs().max())
    return out


def _chunks(data, rig, H: int, W: int, device):
    from imac_data.core.contact.images import chunk_plan

    T = len(data["q"])
    K = rig.intrinsics((H, W)).to(device)
    rd = torch.as_tensor(data["robot_depth"]).to(device)
    Tw = torch.as_tensor(data["T_world_cam"]).to(device)
    gp = torch.as_tensor(data["gripper_points"]).to(device)
    depth = torch.as_tensor(data["ref_depth_mm"].astype(np.float32) / 1000.0).to(device)
    for c, (ref, frames) in enumerate(chunk_plan(T, CHUNK)):
        idx = torch.as_tensor(frames, device=device)
        yield (depth[c], K, Tw[ref], rd[ref] > 0, rd[idx], Tw[idx], gp[idx]), len(frames)


def _agreement(a, b) -> tuple[float, int]:
    """Max |a - b| over entries finite in both, and the count of entries whose kind
    (finite / +inf / NaN) differs."""
    fa, fb = torch.isfinite(a), torch.isfinite(b)
    both = fa & fb
    diff = float((a[both] - b[both]).abs().max()) if bool(both.any()) else 0.0
    kind = lambda x: torch.where(torch.isnan(x), 0, torch.where(torch.isinf(x), 1, 2))  # noqa: E731
    return diff, int((kind(a) != kind(b)).sum())


def _within_tolerance(certified, exact, tol) -> float:
    """Largest violation (metres) of exact <= certified <= exact + max(tol_m, tol_rel * exact)."""
    both = torch.isfinite(certified) & torch.isfinite(exact)
    c, e = certified[both].double(), exact[both].double()
    slack = torch.clamp(torch.maximum(e - c, c - e - torch.clamp(tol[1] * e, min=tol[0])), min=0)
    return float(slack.max()) if len(slack) else 0.0


def contact_figures(rig, data, H: int, W: int, cpu_threads: int, bruteforce_cpu: bool = False) -> dict:
    from imac_data.core.contact.images import DEFAULT_TOLERANCE, contact_chunk

    ws = rig.workspace
    oracle = {}  # chunk -> CPU exact (all cores)
    row: dict = {}
    for label, cores in (("cpu", cpu_threads), ("cpu_all", None)):
        for mode, tol in (("certified", DEFAULT_TOLERANCE), ("exact", None)):
            _progress(f"contact {H}x{W} {label} {mode}")
            for rep in range(2):  # the first pass warms up
                t, frames = 0.0, 0
                for c, (args, n) in enumerate(_chunks(data, rig, H, W, "cpu")):
                    t0 = time.perf_counter()
                    with _cores(cores):  # as the build: KD-tree workers and Python threads, one per core
                        res = contact_chunk(*args, tolerance=tol, workspace=ws)
                    t += time.perf_counter() - t0
                    frames += n
                    if label == "cpu_all" and mode == "exact":
                        oracle[c] = res
            row[f"{label}_{mode}_ms_per_frame"] = 1e3 * t / frames
    if torch.cuda.is_available():
        dev, acc = torch.device("cuda"), "cuda"
    elif bruteforce_cpu:  # the CUDA algorithm on the CPU: checks this script without a GPU
        dev, acc = torch.device("cpu"), "bruteforce_cpu"
    else:
        return row
    for mode, tol in (("certified", DEFAULT_TOLERANCE), ("exact", None)):
        _progress(f"contact {H}x{W} {acc} {mode}")
        if acc == "cuda":
            torch.cuda.reset_peak_memory_stats()
        errors = {"r2s": [0.0, 0], "s2g": [0.0, 0]}
        worst_violation, same_rgb, pixels = 0.0, 0, 0
        for rep in range(2 if acc == "cuda" else 1):  # CUDA: the first pass warms up
            t, frames = 0.0, 0
            for c, (args, n) in enumerate(_chunks(data, rig, H, W, dev)):
                _sync()
                t0 = time.perf_counter()
                res = contact_chunk(*args, tolerance=tol, workspace=ws, method="torch")
                _sync()
                t += time.perf_counter() - t0
                frames += n
                if rep == 0:
                    ref = oracle[c]
                    for stream in ("r2s", "s2g"):
                        got, want = getattr(res, stream).cpu(), getattr(ref, stream)
                        if tol is None:
                            d, k = _agreement(got, want)
                            errors[stream][0] = max(errors[stream][0], d)
                            errors[stream][1] += k
                        else:
                            worst_violation = max(worst_violation, _within_tolerance(got, want, tol))
                    if tol is None:
                        for stream in ("r2s_rgb", "s2g_rgb"):
                            a, b = getattr(res, stream).cpu(), getattr(ref, stream)
                            same_rgb += int((a == b).all(-1).sum())
                            pixels += a[..., 0].numel()
        row[f"{acc}_{mode}_ms_per_frame"] = 1e3 * t / frames
        if acc == "cuda":
            row[f"cuda_{mode}_peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
        if tol is None:
            for stream, (d, k) in errors.items():
                row[f"{acc}_exact_vs_cpu_exact_{stream}_max_abs_diff_m"] = d
                row[f"{acc}_exact_vs_cpu_exact_{stream}_kind_mismatches"] = k
            row[f"{acc}_exact_vs_cpu_exact_rgb_identical_fraction"] = same_rgb / max(pixels, 1)
        else:
            row[f"{acc}_certified_max_tolerance_violation_m"] = worst_violation
    return row


def render_figures(rig, data, H: int, W: int, bruteforce_cpu: bool = False) -> dict:
    """The torch rasteriser on every exported frame, 3 views: wall ms per frame, and its masks and depth
    against the export's (Open3D ray casting)."""
    from imac_data.core.render import RasterRenderer

    if torch.cuda.is_available():
        dev, acc = "cuda", "cuda"
    elif bruteforce_cpu:
        dev, acc = "cpu", "raster_cpu"
    else:
        return {}
    _progress(f"render {H}x{W} {acc}")
    renderer = RasterRenderer(rig.robot, device=dev)
    cams = rig.stream_cameras((H, W))
    q = torch.as_tensor(data["q"]).to(dev)
    if acc == "cuda":
        torch.cuda.reset_peak_memory_stats()
    seconds = _timed(lambda: renderer.render(q, cams), 3 if acc == "cuda" else 1)
    views = renderer.render(q, cams)
    got = torch.stack([views[c].depth.cpu() for c in rig.names], 1)  # (T, V, H, W), as exported
    want = torch.as_tensor(data["robot_depth"])
    a, b = got > 0, want > 0
    both = a & b
    row = {f"{acc}_ms_per_frame": 1e3 * seconds / len(q),
           f"{acc}_mask_iou_vs_raycast": float((both.sum() / (a | b).sum().clamp(min=1))),
           f"{acc}_depth_within_1mm_vs_raycast": float(((got - want).abs()[both] <= 1e-3).float().mean())}
    if acc == "cuda":
        row["cuda_peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return row


def run(inputs: Path, cpu_threads: int = 2, repeats: int = 5, batches=FK_BATCHES, bruteforce_cpu: bool = False) -> dict:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    _progress("loading the rig")
    rig = _load_rig(inputs)
    out = {"cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
           "cpu_threads": cpu_threads, "torch": torch.__version__,
           "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
           "gripper_points": rig.gripper.num_points, "links": len(rig.robot.link_poses(torch.zeros(rig.dof)))}
    sizes = json.loads((inputs / "sizes.json").read_text())
    data = {name: dict(np.load(inputs / f"inputs_{name}.npz")) for name in sizes}
    first = next(iter(sizes))
    _progress("FK vs MuJoCo")
    out["fk_vs_mujoco"] = fk_vs_mujoco(rig, data[first])
    out["fk"] = fk_figures(rig, torch.as_tensor(data[first]["q"]), cpu_threads, repeats, batches)
    out["contact"], out["render"] = {}, {}
    for name, (H, W, _) in sizes.items():
        out["contact"][name] = contact_figures(rig, data[name], H, W, cpu_threads, bruteforce_cpu)
        out["contact"][name]["frames"] = int(len(data[name]["q"]))
        out["render"][name] = render_figures(rig, data[name], H, W, bruteforce_cpu)
    return out


def report(r: dict) -> str:
    lines = [f"{r['gpu'] or 'no GPU'}; CPU {r['cpu']} ({r['cpu_count']} cores); torch {r['torch']}",
             f"FK alone, and FK + camera poses + gripper surface points ({r['links']} links, "
             f"{r['gripper_points']} gripper points), ms per call:",
             f"  {'batch':>6} | {'CPU ' + str(r['cpu_threads']) + ' thr':>17} | {'CPU all cores':>17} | "
             f"{'CUDA':>17} | CUDA f32 err (m)"]
    nan = float("nan")
    for B, row in r["fk"].items():
        cells = [f"{row.get(d + '_fk_ms', nan):>7.2f} {row.get(d + '_fk_points_ms', nan):>9.2f}"
                 for d in ("cpu", "cpu_all", "cuda")]
        lines.append(f"  {B:>6} | " + " | ".join(cells) + f" | {row.get('cuda_max_translation_error_m', nan):.1e}")
    m = r["fk_vs_mujoco"]
    lines.append(f"FK vs MuJoCo's body poses ({m['frames']} frames, {m['bodies']} bodies), max |error| translation (m) "
                 "/ rotation: " + ", ".join(f"{k.removesuffix('_max_translation_error_m')} {v:.1e} / "
                                            f"{m[k.replace('translation_error_m', 'rotation_error')]:.1e}"
                                            for k, v in m.items() if k.endswith("_max_translation_error_m")))
    lines.append("contact images, 3 views, chunks of 8, ms per future frame:")
    for name, row in r["contact"].items():
        lines.append(f"  {name} ({row['frames']} frames): CPU {r['cpu_threads']} threads certified "
                     f"{row['cpu_certified_ms_per_frame']:.1f} / exact {row['cpu_exact_ms_per_frame']:.1f}; CPU all cores "
                     f"{row['cpu_all_certified_ms_per_frame']:.1f} / {row['cpu_all_exact_ms_per_frame']:.1f}")
        for acc in ("cuda", "bruteforce_cpu"):
            if f"{acc}_exact_ms_per_frame" not in row:
                continue
            memory = ({m: f" ({row[f'cuda_{m}_peak_gpu_mb']:.0f} MB peak)" for m in ("certified", "exact")}
                      if acc == "cuda" else {"certified": "", "exact": ""})
            lines.append(f"    {'CUDA' if acc == 'cuda' else 'brute force (the CUDA algorithm) on the CPU'}: certified "
                         f"{row[f'{acc}_certified_ms_per_frame']:.2f} ms{memory['certified']}, exact "
                         f"{row[f'{acc}_exact_ms_per_frame']:.2f} ms{memory['exact']}")
            lines.append(f"    vs CPU exact (KD-tree): r2s max |diff| {row[f'{acc}_exact_vs_cpu_exact_r2s_max_abs_diff_m']:.1e} m, "
                         f"s2g {row[f'{acc}_exact_vs_cpu_exact_s2g_max_abs_diff_m']:.1e} m, kind mismatches "
                         f"{row[f'{acc}_exact_vs_cpu_exact_r2s_kind_mismatches']}/"
                         f"{row[f'{acc}_exact_vs_cpu_exact_s2g_kind_mismatches']}, identical colour pixels "
                         f"{100 * row[f'{acc}_exact_vs_cpu_exact_rgb_identical_fraction']:.3f} %; certified: worst "
                         f"tolerance violation {row[f'{acc}_certified_max_tolerance_violation_m']:.1e} m")
    for name, row in r.get("render", {}).items():
        for acc, label in (("cuda", "CUDA"), ("raster_cpu", "the CPU")):
            if f"{acc}_ms_per_frame" in row:
                lines.append(f"robot raster {name}, 3 views, torch rasteriser on {label}: {row[f'{acc}_ms_per_frame']:.2f} "
                             f"ms per frame; vs Open3D ray casting: mask IoU {row[f'{acc}_mask_iou_vs_raycast']:.6f}, "
                             f"depth within 1 mm on {100 * row[f'{acc}_depth_within_1mm_vs_raycast']:.3f} % of the pixels "
                             "both draw")
    return "\n".join(lines)


def main(argv=None) -> dict | None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.cuda_paths", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("export", help="simulate, render and write the inputs (needs MuJoCo and Open3D)")
    e.add_argument("dir", type=Path)
    e.add_argument("--quick", action="store_true", help=f"one small size, few frames ({QUICK_SIZES})")
    r = sub.add_parser("run", help="time and check FK, the raster and contact on the CPU and on CUDA")
    r.add_argument("dir", type=Path)
    r.add_argument("--cpu-threads", type=int, default=2, help="the CPU row's threads (default 2, as CI)")
    r.add_argument("--repeats", type=int, default=5, help="FK: timed calls per batch, the fastest counts")
    r.add_argument("--batches", type=int, nargs="+", default=list(FK_BATCHES), help="FK batch sizes")
    r.add_argument("--bruteforce-cpu", action="store_true",
                   help="without CUDA: run the CUDA algorithms (brute-force contact, the rasteriser) on the CPU and "
                        "check them the same way")
    r.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    if args.command == "export":
        export(args.dir, QUICK_SIZES if args.quick else SIZES)
        return None
    res = run(args.dir, args.cpu_threads, args.repeats, tuple(args.batches), args.bruteforce_cpu)
    print(report(res))
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
