"""The benchmark runner in CI: ``python -m benchmarks.run --quick`` (tiny resolutions, a few
frames, every section once) into a temporary directory, so ``make bench`` cannot rot.

Not a timing test: nothing here asserts how fast anything is. It checks that the run
completes, that ``latest.json`` carries every headline key as a finite number (or says
why it could not be measured in the quick workload), that ``latest.md`` shows them, and
that the committed results in ``benchmarks/results/`` are left alone. About 90 s on
the 2-core CI machine (five tiny whole builds: the workload's, the two episode lengths, and the
workload's episodes by ``benchmarks.same_host`` with HEAD as the baseline and by this checkout).
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

from benchmarks import contact_profile, suite_profile
from benchmarks.run import REQUIRED_STRINGS, RESULTS
from benchmarks.run_report import REQUIRED_NUMBERS

REPO = Path(__file__).resolve().parent.parent
# The quick workload records only a few steps: no finger gets within 5 cm of the cube.
MAY_BE_UNMEASURED_IN_QUICK = {"contact_err_max_mm_under_5cm", "fps_ray_240"}  # no Ray build in --quick


def _committed() -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(RESULTS.glob("latest.*"))} if RESULTS.is_dir() else {}


def _worktrees() -> str:
    return subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout


def test_quick_benchmark_writes_every_figure(tmp_path):
    before = _committed()
    worktrees = _worktrees()
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    # HEAD as the baseline: the run's own episodes also built by a worktree's command line and by ours
    proc = subprocess.run([sys.executable, "-m", "benchmarks.run", "--quick", "--baseline", "HEAD", "--out", str(tmp_path)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"benchmark failed:\n{proc.stderr[-6000:]}"

    result = json.loads((tmp_path / "latest.json").read_text())
    assert result["quick"] is True
    for key in REQUIRED_STRINGS:
        assert isinstance(result[key], str) and result[key], key
    assert result["commit"] == "unknown" or len(result["commit"]) == 40
    for key in REQUIRED_NUMBERS:
        assert key in result, key
        value = result[key]
        if value is None:
            assert key in MAY_BE_UNMEASURED_IN_QUICK, f"{key} not measured: {result['not_measured'].get(key)}"
            assert result["not_measured"][key]
        else:
            assert isinstance(value, (int, float)) and math.isfinite(value), (key, value)
    assert len(result["load_avg"]["start"]) == 3 and len(result["load_avg"]["end"]) == 3

    # plausibility, not speed: every figure is in its physical range
    positive = ("fps_total_240", "cpu_ms_per_frame_240", "peak_mem_mb_per_worker",
                "long_episode_peak_mb", "short_episode_peak_mb", "render_ms_per_view_240", "render_ratio_vs_mujoco",
                "contact_fps_cpu", "contact_ratio_vs_reference")
    for key in positive:
        assert result[key] > 0, key
    for key in ("mask_iou_head", "mask_iou_wrist_min"):
        assert 0.9 <= result[key] <= 1.0, key  # the renderer matches MuJoCo's robot pixels
    assert 0 <= result["depth_err_median_mm"] <= result["depth_err_p99_mm"]
    assert result["depth_err_p99_mm"] < result["depth_err_p99_mm_lerobot_default"]
    for b in result["builds"]:
        assert b["frames"] > 0 and b["bytes_per_frame"]["total"] > 0 and b["cpu_ms_per_frame"] > 0
    assert {(b["executor"], b["workers"]) for b in result["builds"]} == {("local", 1)}
    # the stage table comes from the build's own timings: every pipeline stage is there
    stages = next(iter(result["stages"].values()))["rows"]
    for stage in ("setup", "read", "fk", "render", "depth", "contact", "encode", "write", "merge", "validate"):
        assert stages[stage]["cpu_ms_per_frame"] >= 0 and stages[stage]["wall_ms_per_frame"] > 0, stage
    assert set(result["episode_length"]["rows"]) == {"8", "24"}

    # beside the baseline: both revisions built the same episodes, each with its CPU and memory
    same = result["same_host"]
    assert sorted(b["revision"] for b in same["builds"]) == ["baseline", "this"]
    assert len({b["frames"] for b in same["builds"]}) == 1 and same["builds"][0]["frames"] > 0
    for b in same["builds"]:
        assert b["cpu_s"] > 0 and b["peak_rss_mb"] > 100 and b["build_s"] > 0
    (summary,) = same["summary"].values()
    assert summary["fps_ratio_best"] > 0 and len(summary["pairs"]) == 1
    assert _worktrees() == worktrees, "the baseline's worktree is removed"

    md = (tmp_path / "latest.md").read_text()
    for key in REQUIRED_NUMBERS:
        assert f"`{key}`" in md, key
    assert "## Against `HEAD` on this machine" in md and "| 48x64 | 0 | 1 | baseline |" in md
    assert _committed() == before, "the quick run must not touch benchmarks/results/"


def test_cuda_paths_export_and_run_check_against_their_oracles(tmp_path):
    """``benchmarks.cuda_paths`` (the GPU machine's benchmark) end to end on the CPU:
    export a tiny episode, then run with ``--bruteforce-cpu`` (the CUDA algorithm on the
    CPU). FK is checked against MuJoCo's body poses; the brute-force contact distances
    against the KD-tree's, exactly (both are exact algorithms in float64); the rasteriser against Open3D's
    ray casting."""
    from benchmarks import cuda_paths

    cuda_paths.export(tmp_path, cuda_paths.QUICK_SIZES)
    r = cuda_paths.run(tmp_path, cpu_threads=1, repeats=1, batches=(1, 3), bruteforce_cpu=True)
    m = r["fk_vs_mujoco"]
    assert m["bodies"] == 22 and m["frames"] == 9
    for key, value in m.items():
        if key.endswith("_max_translation_error_m"):
            assert value < 1e-6, (key, value)
    (row,) = r["contact"].values()
    prefix = "cuda" if torch_cuda_available() else "bruteforce_cpu"
    assert row[f"{prefix}_exact_vs_cpu_exact_r2s_max_abs_diff_m"] == 0.0
    assert row[f"{prefix}_exact_vs_cpu_exact_s2g_max_abs_diff_m"] == 0.0
    assert row[f"{prefix}_exact_vs_cpu_exact_r2s_kind_mismatches"] == 0
    assert row[f"{prefix}_exact_vs_cpu_exact_s2g_kind_mismatches"] == 0
    assert row[f"{prefix}_exact_vs_cpu_exact_rgb_identical_fraction"] == 1.0
    assert row[f"{prefix}_certified_max_tolerance_violation_m"] < 1e-6  # float32 rounding
    (raster,) = r["render"].values()  # the GPU build's rasteriser against the export's ray casting
    prefix = "cuda" if torch_cuda_available() else "raster_cpu"
    assert raster[f"{prefix}_mask_iou_vs_raycast"] >= 0.9999 and raster[f"{prefix}_depth_within_1mm_vs_raycast"] >= 0.999
    assert "FK vs MuJoCo" in cuda_paths.report(r) and "torch rasteriser" in cuda_paths.report(r)


def torch_cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def test_contact_profile_splits_the_stage_into_parts_that_add_up():
    """benchmarks.contact_profile at a tiny size: the searches, the tiles' passes and the rest are each
    measured and sum to the profiled whole (not a timing test: no figure is compared with a speed)."""
    r = contact_profile.run("48x64", max_steps=10)
    parts = ("searches_ms_per_frame", "certified_tiles_other_ms_per_frame", "rest_ms_per_frame")
    assert r["future_frames"] > 0 and all(r[k] > 0 for k in parts)
    assert math.isclose(sum(r[k] for k in parts), r["profiled_ms_per_frame"], rel_tol=1e-9)
    assert 0 < r["searches_share"] < 1 and "KD-tree searches" in contact_profile.report(r)


def test_the_suite_profile_counts_every_python_process_a_test_starts(tmp_path, capsys):
    """benchmarks.suite_profile on one test that starts one Python process (the layer check's import probe): the
    pytest process and that child are both logged with their CPU and imports, the test's duration is read back,
    and the JSON keeps it."""
    test = "tests/test_layers.py::test_reading_and_training_modules_import_no_renderer_robot_or_sharding_library"
    assert suite_profile.main(["--json", str(tmp_path / "p.json"), "--", "-q", "-p", "no:cacheprovider", test]) == 0
    result = json.loads((tmp_path / "p.json").read_text())
    assert result["outcome"] == ["1 passed"] and result["returncode"] == 0
    assert list(result["tests"]) == [test] and result["tests_sum_s"] > 0
    kinds = result["kinds"]
    assert result["processes"] == 2 and kinds["-c"]["processes"] == 1  # pytest itself and the probe it ran
    assert sum(k["processes"] for k in kinds.values()) == 2 and result["cpu_s"] > 0
    assert "2 Python processes" in capsys.readouterr().out
