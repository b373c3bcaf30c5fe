"""A build worker's peak memory does not grow with the episode's length.

One recorded episode is tiled (played forward and backward) into a short and a long
episode; each is built into a complete one-episode dataset (what a build worker does:
read, FK, render, depth, contact, encode every stream, LeRobot's writer) in a fresh
process, whose peak resident memory (``VmHWM``) is the measurement. The pipeline
before streaming held every frame of an episode and grew by about 1 MB per frame at this
resolution (64x80), i.e. by some 150 MB between the two episodes; the bound below is a few
frames' worth. No timing is asserted.
"""

import json
import subprocess
import sys
from pathlib import Path

import yaml

from imac_data.recipes import RECIPES_DIR
from imac_data.sources.hdf5 import EpisodeReader, tile_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset

REPO = Path(__file__).resolve().parent.parent
SHORT, LONG = 32, 192
GROWTH_LIMIT_MB = 50.0

WORKER = """
import json, sys
from pathlib import Path
from imac_data.console import quiet_libraries
from imac_data.dataset.ingest import IngestOptions
from imac_data.build.streams import write_episode_dataset
from imac_data.recipes import load_recipe
from imac_data.core.rig import Rig
quiet_libraries()
episode, recipe, out = (Path(a) for a in sys.argv[1:4])
r = load_recipe(recipe)
rig = Rig.from_recipe(r, episode.parent / "calibration.json")
options = IngestOptions(fps=25, task="t", robot_type=rig.robot.name, state_names=rig.state_names)
write_episode_dataset(episode, out, "local/mem", rig, r.augment, options)
from imac_data.build.workers import peak_rss_mb  # VmHWM: ru_maxrss would carry the test process's peak over
print(json.dumps({"peak_mb": peak_rss_mb()}))
"""


def peak_mb(episode: Path, recipe: Path, out: Path) -> float:
    proc = subprocess.run([sys.executable, "-c", WORKER, str(episode), str(recipe), str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])["peak_mb"]


def test_worker_peak_memory_does_not_grow_with_episode_length(tmp_path):
    src = tmp_path / "src"
    record_dataset(SimConfig(num_episodes=1, width=80, height=64, max_steps=48), src, progress=False)
    episodes = {}
    for n in (SHORT, LONG):
        d = tmp_path / f"ep{n}"
        d.mkdir()
        (d / "calibration.json").write_text((src / "calibration.json").read_text())
        episodes[n] = tile_episode(src / "episode_0.hdf5", d / "episode_0.hdf5", n)
    with EpisodeReader(episodes[LONG]) as ep:
        assert ep.num_frames == LONG
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 64, "width": 80, "contact_chunk": 8}
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(data))
    short = peak_mb(episodes[SHORT], recipe, tmp_path / "out_short")
    long = peak_mb(episodes[LONG], recipe, tmp_path / "out_long")
    print(f"peak RSS {short:.0f} MB ({SHORT} frames), {long:.0f} MB ({LONG} frames)")
    assert long - short < GROWTH_LIMIT_MB, (f"peak RSS grew from {short:.0f} MB ({SHORT} frames) to {long:.0f} MB "
                                            f"({LONG} frames)")
