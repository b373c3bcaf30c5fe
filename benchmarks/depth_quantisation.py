"""Depth colour codec: 8-bit quantisation step per preset, and encode/decode throughput.

    .venv/bin/python benchmarks/depth_quantisation.py [--markdown out.md] [--frames 8]

Quantisation step = metres per one 8-bit code step along the colour walk (one LSB
of one channel) at a given depth, two ways:

* analytic: ``1 / (1785 f'(d))`` (``DepthCodec.quantisation_step``);
* measured: decode the uint8 colours of the codes on either side of ``d`` (colours
  built here from the walk corners, not by the encoder) and difference them.

It also measures the worst uint8 round-trip error in a +-1 % window around each
depth (should be half a step), checks the steps docs/dataset-format.md quotes for the
``manipulation`` preset, and times encode/decode (numpy, torch CPU, CUDA if present).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from imac_data.core.depth import CORNERS, N_CODES, PRESETS, DepthCodec

DEPTHS = [0.05, 0.1, 0.2, 0.5, 1.0, 1.2, 1.5, 2.0, 5.0, 10.0, 20.0]
# docs/dataset-format.md, manipulation preset: depth (m) -> quoted 8-bit step (mm).
QUOTED_STEPS_MM = {0.1: "0.4", 1.0: "2", 1.2: "2.8", 2.0: "13"}


def code_colour(code: np.ndarray) -> np.ndarray:
    """uint8 colour of 8-bit walk code(s) 0..1785, straight from the corner table."""
    code = np.asarray(code, dtype=np.int64)
    k = np.minimum(code // 255, 6)
    frac = code - 255 * k
    return (CORNERS[k] * 255 + frac[..., None] * (CORNERS[k + 1] - CORNERS[k])).astype(np.uint8)


def step_rows(codec: DepthCodec) -> list[dict]:
    rows = []
    for d in DEPTHS:
        analytic = float(codec.quantisation_step(d))
        code = 7 * 255 * float(codec.transform(d))
        saturated = d > codec.max_depth
        row = {"depth": d, "code": code, "analytic_mm": analytic * 1e3, "saturated": saturated}
        if saturated:
            row.update(measured_mm=float("nan"), max_err_mm=float("nan"))
        else:
            n = int(np.clip(round(code), 2, N_CODES - 2))
            around = codec.decode(code_colour([n - 1, n + 1])).astype(np.float64)
            row["measured_mm"] = (around[1] - around[0]) / 2 * 1e3
            window = np.linspace(0.99 * d, min(1.01 * d, codec.max_depth), 4001)
            back = codec.decode(codec.encode_uint8(window)).astype(np.float64)
            row["max_err_mm"] = float(np.abs(back - window).max()) * 1e3
        rows.append(row)
    return rows


def fmt_mm(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x:.3g}" if x < 1000 else f"{x:.3e}"


def quantisation_table(codec: DepthCodec) -> tuple[list[str], list[list[str]]]:
    header = ["depth (m)", "code", "step mm (analytic)", "step mm (measured)", "max uint8 round-trip err mm"]
    body = []
    for r in step_rows(codec):
        if r["saturated"]:
            body.append([f"{r['depth']:g}", "1784 (saturated)", fmt_mm(r["analytic_mm"]),
                         f"- (beyond max depth {codec.max_depth:.3f} m)", "-"])
        else:
            body.append([f"{r['depth']:g}", f"{r['code']:.1f}", fmt_mm(r["analytic_mm"]),
                         fmt_mm(r["measured_mm"]), fmt_mm(r["max_err_mm"])])
    return header, body


def claims_check(codec: DepthCodec) -> tuple[list[str], list[list[str]]]:
    header = ["depth (m)", "quoted step (mm)", "measured step (mm)", "holds to quoted precision"]
    body = []
    for d, quoted in QUOTED_STEPS_MM.items():
        step_mm = float(codec.quantisation_step(d)) * 1e3
        decimals = len(quoted.split(".")[1]) if "." in quoted else 0
        holds = round(step_mm, decimals) == float(quoted)
        body.append([f"{d:g}", quoted, f"{step_mm:.3f}", "yes" if holds else "NO"])
    return header, body


def time_best(fn, *args, repeats: int, sync=None) -> float:
    fn(*args)
    if sync:
        sync()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        if sync:
            sync()
        best = min(best, time.perf_counter() - t0)
    return best


def throughput(frames: int, height: int, width: int, repeats: int) -> tuple[list[str], list[list[str]]]:
    codec = DepthCodec()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.1, 2.0, (frames, height, width)).astype(np.float32)
    depth[:, :8] = 0.0  # a few invalid rows, as in real depth
    rgb = codec.encode(depth)
    rgb8 = codec.encode_uint8(depth)
    backends = [("numpy", lambda a: a, None)]
    backends.append((f"torch CPU ({torch.get_num_threads()} threads)", torch.from_numpy, None))
    if torch.cuda.is_available():
        backends.append((f"torch {torch.cuda.get_device_name()}", lambda a: torch.from_numpy(a).cuda(),
                         torch.cuda.synchronize))
    header = ["backend", "encode float (Mpx/s)", "encode_uint8 (Mpx/s)", "decode uint8 (Mpx/s)",
              "decode float (Mpx/s)"]
    body = []
    mpx = depth.size / 1e6
    for name, convert, sync in backends:
        d, c, c8 = convert(depth), convert(rgb), convert(rgb8)
        cols = [name]
        for fn, arg in ((codec.encode, d), (codec.encode_uint8, d), (codec.decode, c8), (codec.decode, c)):
            cols.append(f"{mpx / time_best(fn, arg, repeats=repeats, sync=sync):.1f}")
        body.append(cols)
    return header, body


def render(header: list[str], body: list[list[str]], markdown: bool) -> str:
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(row) + " |" for row in body]
        return "\n".join(lines)
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body)]
    fmt = "  ".join(f"{{:>{w}}}" for w in widths)
    return "\n".join([fmt.format(*header), *(fmt.format(*row) for row in body)])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--markdown", type=Path, help="also write the report as Markdown here")
    parser.add_argument("--frames", type=int, default=8, help="frames per timing batch (default 8)")
    parser.add_argument("--size", default="480x640", help="frame HxW for timing (default 480x640)")
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats, best kept (default 5)")
    args = parser.parse_args(argv)
    height, width = (int(v) for v in args.size.lower().split("x"))

    codecs = {name: DepthCodec.preset(name) for name in PRESETS}
    sections = []
    for name, codec in codecs.items():
        note = (f"lam={codec.lam:g}, c={codec.c:.4g}; min depth {codec.min_depth * 1e3:.3g} mm (code 1), "
                f"max depth {codec.max_depth:.4g} m (code 1784; deeper saturates to it). "
                "code = 8-bit position along the walk (0 = black = invalid).")
        sections.append((f"8-bit quantisation step: {name}", note, quantisation_table(codec)))
    sections.append(("the quoted steps (manipulation)", "", claims_check(codecs["manipulation"])))
    sections.append(
        (f"Throughput ({args.frames} x {height}x{width} frames, best of {args.repeats})",
         f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads, "
         f"numpy {np.__version__}, torch {torch.__version__}",
         throughput(args.frames, height, width, args.repeats)))

    for title, note, (header, body) in sections:
        print(f"\n== {title} ==")
        if note:
            print(note)
        print(render(header, body, markdown=False))
    if args.markdown:
        md = ["# Depth codec: quantisation and throughput", ""]
        for title, note, (header, body) in sections:
            md += [f"## {title}", ""] + ([note, ""] if note else []) + [render(header, body, True), ""]
        args.markdown.write_text("\n".join(md))
        print(f"\nwrote {args.markdown}")


if __name__ == "__main__":
    main()
