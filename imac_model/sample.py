"""Generate a future chunk for a dataset episode and show it beside the recording:
``python -m imac_model.sample --checkpoint runs/x --episode 8 [--chunk 3] [--out sample.mp4]``.

``--chunks N`` rolls out N chunks autoregressively (:func:`imac_model.rollout.sample_rollout`):
each next reference is the last generated frame, and the motion and contact images are
rebuilt online from the generated depth and the recorded actions at every chunk boundary
(:mod:`imac_model.online_controls`).

The mp4 shows, per future frame, the generated mosaic, the recorded mosaic and the
control images the model was given (one row per stream, views side by side).
``--png`` also writes a still: rows = future frames (first, middle, last), columns =
generated | recorded | motion image (for the README).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_model import mosaic
from imac_model.batch import ChunkBatch
from imac_model.checkpoint import load_world_model, resolve_checkpoint, run_config_of
from imac_model.config import DataConfig, ModelSpec
from imac_model.data import ChunkDataset, open_metadata, resolve_layout

LABEL_COLOUR = (255, 255, 255)


@dataclass
class ChunkSample:
    generated: torch.Tensor  # (H, 3, 2h, V w) in [0, 1]
    recorded: torch.Tensor  # (H, 3, 2h, V w)
    controls: dict[str, torch.Tensor]  # stream -> (H, V, 3, h, w) per view
    valid: torch.Tensor  # (H,) bool
    reference: torch.Tensor  # (3, 2h, V w): the frame the chunk starts from
    episode: int
    reference_frame: int


def open_chunks(spec: ModelSpec, dataset: str, root: str | None, episodes=None) -> ChunkDataset:
    """The chunks of ``dataset`` laid out for ``spec`` (checked against it)."""
    from imac_model.backbones import spatial_multiple, temporal_factor

    data = DataConfig(dataset=dataset, root=root, view_height=spec.view_height, view_width=spec.view_width,
                      chunk=spec.chunk, views=spec.views, cache="none")
    meta = open_metadata(data)
    layout = resolve_layout(meta.info, data, spec.conditioning.streams, spatial_multiple=spatial_multiple(spec.backbone),
                            temporal_factor=temporal_factor(spec.backbone), mode=spec.conditioning.mode)
    if episodes is not None:
        bad = [e for e in episodes if not 0 <= e < meta.total_episodes]
        if bad:
            raise InputError(f"--episode {bad[0]}: the dataset has episodes 0..{meta.total_episodes - 1}")
    return ChunkDataset(dataset, layout, root=root, episodes=episodes, cache="none")


def sample_chunk(model, chunks: ChunkDataset, episode: int, chunk: int = 0, *, steps: int | None = None,
                 seed: int = 0) -> ChunkSample:
    items = chunks.episode_chunks(episode)
    if not 0 <= chunk < len(items):
        raise InputError(f"--chunk {chunk}: episode {episode} has chunks 0..{len(items) - 1}")
    batch: ChunkBatch = chunks.batch([items[chunk]])
    device = next(model.parameters()).device
    out = model.sample(batch.to(device), steps=steps, generator=torch.Generator().manual_seed(seed))
    V = len(model.spec.views)
    return ChunkSample(generated=out.frames[0].cpu(), recorded=batch.future[0],
                       controls={s: mosaic.control_views(c[0], V) for s, c in batch.controls.items()},
                       valid=batch.valid_mask()[0], reference=batch.reference[0], episode=episode, reference_frame=int(batch.frame_index[0]))


def online_controls_for(spec: ModelSpec, chunks: ChunkDataset, run: dict | None = None):
    """The dataset's :class:`~imac_model.online_controls.OnlineControls` for a model (None for a
    model without control streams), with the run's ``rollout`` settings."""
    from imac_model.config import RolloutConfig, parse
    from imac_model.online_controls import OnlineControls

    if not spec.conditioning.streams:
        return None
    rc = parse(RolloutConfig, (run or {}).get("rollout") or {}, "rollout")
    return OnlineControls.from_dataset(chunks.lerobot.root, spec, info=chunks.lerobot.meta.info,
                                       resolution=rc.resolution, max_walk_distance=rc.max_walk_distance)


def sample_rollout_chunks(model, chunks: ChunkDataset, episode: int, chunk: int, n: int, online, *,
                          steps: int | None = None, seed: int = 0, recorded_states: bool = False
                          ) -> tuple[ChunkSample, list[ChunkSample], list[float]]:
    """Roll out ``n`` chunks of ``episode`` from chunk ``chunk``'s recorded reference
    (:func:`imac_model.rollout.sample_rollout`): the first chunk gets the dataset's controls,
    every later one controls rebuilt online from the generated depth and the recorded actions,
    with the robot state at each boundary = the last commanded configuration (or the recorded
    state with ``recorded_states``). Returns the whole rollout as one :class:`ChunkSample`
    (n x H frames), one per chunk, and the share of invalid generated depth per rebuild."""
    from imac_model.rollout import sample_rollout

    items = chunks.episode_chunks(episode)
    if chunk < 0 or chunk + n > len(items):
        raise InputError(f"--chunk {chunk} --chunks {n}: episode {episode} has chunks 0..{len(items) - 1}")
    batches = [chunks.batch([items[chunk + i]]) for i in range(n)]
    device = next(model.parameters()).device
    first = batches[0].to(device)
    actions = torch.stack([b.actions for b in batches], dim=1).to(device)
    states = None
    if recorded_states:
        if any(b.state is None for b in batches):
            raise InputError("--recorded-states: the dataset has no observation.state")
        states = torch.stack([b.state for b in batches], dim=1)
    out = sample_rollout(model, first, actions, online, states=states, steps=steps, seed=seed)
    V = len(model.spec.views)
    per_chunk = []
    for i, b in enumerate(batches):
        per_chunk.append(ChunkSample(
            generated=out.frames[0, i].cpu(), recorded=b.future[0],
            controls={s: mosaic.control_views(c[0].cpu(), V) for s, c in out.controls[i].items()},
            valid=b.valid_mask()[0], reference=out.references[i][0].cpu(), episode=episode,
            reference_frame=int(b.frame_index[0])))
    whole = ChunkSample(generated=torch.cat([c.generated for c in per_chunk]),
                        recorded=torch.cat([c.recorded for c in per_chunk]),
                        controls={s: torch.cat([c.controls[s] for c in per_chunk]) for s in per_chunk[0].controls},
                        valid=torch.cat([c.valid for c in per_chunk]), reference=per_chunk[0].reference,
                        episode=episode, reference_frame=per_chunk[0].reference_frame)
    return whole, per_chunk, out.invalid_depth


def robot_region_errors(s: ChunkSample) -> dict[str, float]:
    """Pixel MSE against the recording over the valid future frames: the whole mosaic, and
    the RGB row inside the future robot (where the motion images are not black), for the
    generated frames and for a baseline that copies the reference frame. A model that puts
    the robot where the motion images say beats the copy inside the robot."""
    V = s.controls["motion"].shape[1] if "motion" in s.controls else None
    out = {"mse": float(((s.generated - s.recorded) ** 2)[s.valid].mean()),
           "mse_copy_reference": float(((s.reference - s.recorded) ** 2)[s.valid].mean())}
    if V is None:
        return out
    h = s.recorded.shape[-2] // 2
    robot = mosaic.controls(s.controls["motion"]).amax(dim=1)[:, :h] > 0.02  # (H, h, V w)
    robot = robot & s.valid[:, None, None]
    if robot.any():
        rgb = lambda x: x[..., :h, :]  # noqa: E731
        err = lambda a: float((((rgb(a) - rgb(s.recorded)) ** 2).mean(dim=1))[robot].mean())  # noqa: E731
        out["mse_robot"] = err(s.generated)
        out["mse_robot_copy_reference"] = err(s.reference.expand_as(s.recorded))
    return out


def _u8(x: torch.Tensor) -> np.ndarray:
    """(3, H, W) in [0, 1] -> (H, W, 3) uint8."""
    return (x.clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy()


def label(img: np.ndarray, text: str, *, scale: float | None = None) -> np.ndarray:
    """``text`` written on the top-left of ``img`` (H, W, 3) uint8, white with a black outline.
    The font grows with the image height (``scale``: fixed instead) and shrinks to fit the
    width (a one-view mosaic is narrow); below a legible size the text is cut with '~'."""
    import cv2

    font, img = cv2.FONT_HERSHEY_SIMPLEX, np.ascontiguousarray(img)
    scale = scale or max(img.shape[0] / 400, 0.35)
    room = img.shape[1] - 8
    width = cv2.getTextSize(text, font, scale, 1)[0][0]
    if width > room:
        scale = max(0.95 * scale * room / width, 0.25)  # text width is not quite linear in the scale
        while len(text) > 1 and cv2.getTextSize(text, font, scale, 1)[0][0] > room:
            text = text[:-2] + "~"
    y = 4 + cv2.getTextSize("Ag", font, scale, 1)[0][1]
    cv2.putText(img, text, (4, y), font, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, y), font, scale, LABEL_COLOUR, 1, cv2.LINE_AA)
    return img


def _cell(x: torch.Tensor, text: str, scale: int) -> np.ndarray:
    """A panel enlarged ``scale`` times (nearest pixel), then labelled at that size."""
    img = _u8(x)
    if scale > 1:
        img = img.repeat(scale, axis=0).repeat(scale, axis=1)
    return label(img, text)


def _controls_block(controls: dict[str, torch.Tensor], k: int, height: int, scale: int) -> np.ndarray | None:
    if not controls:
        return None
    rows = [_cell(torch.cat(c[k].unbind(0), dim=-1), s, scale) for s, c in controls.items()]
    block = np.concatenate(rows, axis=0)
    if block.shape[0] < height:
        block = np.concatenate([block, np.zeros((height - block.shape[0], *block.shape[1:]), np.uint8)], axis=0)
    return block


def frame_panel(s: ChunkSample, k: int, scale: int = 1) -> np.ndarray:
    """One video frame: generated | recorded | controls of future frame ``k``, enlarged ``scale`` times."""
    gen = _cell(s.generated[k], f"generated t+{k + 1}", scale)
    rec = _cell(s.recorded[k], "recorded" + ("" if s.valid[k] else " (padded)"), scale)
    parts = [gen, rec]
    ctrl = _controls_block(s.controls, k, gen.shape[0], scale)
    height = max(p.shape[0] for p in parts + ([ctrl] if ctrl is not None else []))
    if ctrl is not None:
        parts.append(ctrl)
    parts = [np.concatenate([p, np.zeros((height - p.shape[0], *p.shape[1:]), np.uint8)]) if p.shape[0] < height
             else p for p in parts]
    return np.concatenate(parts, axis=1)


def _even(img: np.ndarray) -> np.ndarray:
    return img[: img.shape[0] // 2 * 2, : img.shape[1] // 2 * 2]  # yuv420p needs even sides


def write_mp4(s: ChunkSample, path: Path, fps: float, scale: int = 2) -> Path:
    from imac_data.video_streams import VideoEncoding, encode_video

    frames = np.stack([_even(frame_panel(s, k, scale)) for k in range(len(s.generated))])
    return encode_video(path, frames, fps=max(int(round(fps)), 1),
                        encoding=VideoEncoding(codec="libx264", pix_fmt="yuv420p", crf=18, qp=None))


def write_png(s: ChunkSample, path: Path, scale: int = 2) -> Path:
    import cv2

    H = len(s.generated)
    rows = []
    for k in sorted({0, H // 2 - 1, H - 1}):
        row = [_cell(s.generated[k], f"generated t+{k + 1}", scale), _cell(s.recorded[k], f"recorded t+{k + 1}", scale)]
        if "motion" in s.controls:
            row.append(_cell(mosaic.controls(s.controls["motion"][k]), "motion image", scale))
        rows.append(np.concatenate(row, axis=1))
    img = _even(np.concatenate(rows, axis=0))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path


def _summary(e: dict) -> str:
    robot = (f"; inside the future robot {e['mse_robot']:.4f} (copying the reference: "
             f"{e['mse_robot_copy_reference']:.4f})" if "mse_robot" in e else "")
    return f"pixel MSE vs recorded {e['mse']:.4f} (copying the reference: {e['mse_copy_reference']:.4f}){robot}"


def evaluate_episodes(model, chunks: ChunkDataset, episodes, *, steps=None, seed: int = 0, progress: bool = True):
    """Mean :func:`robot_region_errors` over every chunk of ``episodes``."""
    from tqdm.auto import tqdm

    jobs = [(e, c) for e in episodes for c in range(len(chunks.episode_chunks(e)))]
    rows = [robot_region_errors(sample_chunk(model, chunks, e, c, steps=steps, seed=seed))
            for e, c in tqdm(jobs, desc="sampling chunks", disable=not progress)]
    keys = set.intersection(*(set(r) for r in rows))
    return {k: float(np.mean([r[k] for r in rows])) for k in sorted(keys)} | {"chunks": len(rows)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m imac_model.sample", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="checkpoint directory, or a run directory (latest checkpoint)")
    p.add_argument("--episode", type=int, nargs="+", required=True, help="episode(s); several only with --evaluate")
    p.add_argument("--chunk", type=int, default=0, help="which chunk of the episode (default: the first)")
    p.add_argument("--chunks", type=int, default=1,
                   help="roll out this many chunks autoregressively from --chunk, rebuilding the controls from the "
                        "generated depth at every chunk boundary (default 1)")
    p.add_argument("--recorded-states", action="store_true",
                   help="with --chunks: the robot state at each boundary is the recorded one, not the last command")
    p.add_argument("--evaluate", action="store_true",
                   help="no video: sample every chunk of the episodes and print the mean errors")
    p.add_argument("--dataset", help="LeRobot repo id (default: the one the model was trained on)")
    p.add_argument("--root", help="dataset directory (default: the training run's)")
    p.add_argument("--out", help="mp4 path (default: <checkpoint>/samples/episode_<N>_chunk_<C>.mp4)")
    p.add_argument("--png", help="also write a still of the first, middle and last future frame here")
    p.add_argument("--steps", type=int, help="Euler steps (default: the model's flow.sample_steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weights", choices=("ema", "raw"), default="ema")
    p.add_argument("--scale", type=int, default=2, help="pixel upscale of the written images")
    args = p.parse_args(argv)
    if len(args.episode) > 1 and not args.evaluate:
        p.error("several --episode values need --evaluate")
    try:
        path = resolve_checkpoint(args.checkpoint)
        model, spec = load_world_model(path, weights=args.weights)
        run = run_config_of(path) or {}
        dataset = args.dataset or spec.dataset
        root = args.root if args.root is not None else (run.get("data", {}).get("root") if not args.dataset else None)
        chunks = open_chunks(spec, dataset, root, episodes=args.episode)
        if args.chunks < 1:
            raise InputError(f"--chunks {args.chunks}: must be >= 1")
        if args.chunks > 1:
            return _rollout_main(args, model, spec, chunks, run, path)
        if args.evaluate:
            e = evaluate_episodes(model, chunks, args.episode, steps=args.steps, seed=args.seed)
            print(f"{e['chunks']} chunks of episodes {args.episode} ({path}): {_summary(e)}")
            return 0
        episode = args.episode[0]
        s = sample_chunk(model, chunks, episode, args.chunk, steps=args.steps, seed=args.seed)
        out = Path(args.out) if args.out else path / "samples" / f"episode_{episode}_chunk_{args.chunk}.mp4"
        out.parent.mkdir(parents=True, exist_ok=True)
        write_mp4(s, out, spec.fps, args.scale)
        if args.png:
            write_png(s, Path(args.png), args.scale)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}" + (f" and {args.png}" if args.png else "") + f" (episode {episode}, reference frame "
          f"{s.reference_frame}, {int(s.valid.sum())} future frames): {_summary(robot_region_errors(s))}")
    return 0


def _rollout_main(args, model, spec, chunks, run, path) -> int:
    online = online_controls_for(spec, chunks, run)
    if args.evaluate:
        per_index: dict[int, list[float]] = {}
        for e in args.episode:
            n_items = len(chunks.episode_chunks(e))
            for start in range(0, n_items - args.chunks + 1, args.chunks):
                _, parts, _ = sample_rollout_chunks(model, chunks, e, start, args.chunks, online, steps=args.steps,
                                                    seed=args.seed, recorded_states=args.recorded_states)
                for i, part in enumerate(parts):
                    per_index.setdefault(i, []).append(robot_region_errors(part)["mse"])
        print(f"{len(per_index.get(0, []))} rollouts of {args.chunks} chunks, episodes {args.episode} ({path}): "
              "pixel MSE vs recorded per chunk " + ", ".join(f"{i + 1}: {np.mean(v):.4f}" for i, v in sorted(per_index.items())))
        return 0
    episode = args.episode[0]
    whole, parts, invalid = sample_rollout_chunks(model, chunks, episode, args.chunk, args.chunks, online,
                                                  steps=args.steps, seed=args.seed,
                                                  recorded_states=args.recorded_states)
    out = (Path(args.out) if args.out else
           path / "samples" / f"episode_{episode}_chunk_{args.chunk}_x{args.chunks}.mp4")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_mp4(whole, out, spec.fps, args.scale)
    if args.png:
        write_png(whole, Path(args.png), args.scale)
    errors = ", ".join(f"{i + 1}: {robot_region_errors(p)['mse']:.4f}" for i, p in enumerate(parts))
    extra = f"; invalid generated depth at the boundaries {np.round(invalid, 4).tolist()}" if invalid else ""
    print(f"wrote {out}" + (f" and {args.png}" if args.png else "") + f" (episode {episode}, {args.chunks} chunks "
          f"from reference frame {whole.reference_frame}): pixel MSE vs recorded per chunk {errors}{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
