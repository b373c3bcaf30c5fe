"""The dataset card (README.md of a built dataset), rendered from ``dataset_cards/``.

The same text goes to the hub: ``push_to_hub`` passes it to LeRobot's own card as its
``dataset_description``.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import jinja2

from imac_data import lerobot_compat as lr
from imac_data.dataset.info import imac_block, read_info
from imac_data.layout import IMAGE_PREFIX, STATE

TEMPLATE = Path(__file__).resolve().parents[2] / "dataset_cards" / "imac_dataset_card.md"


def policy_input_features(info: dict) -> dict[str, dict]:
    """What a LeRobot policy trained on this dataset should see: the original cameras and the
    joint state, as ``--policy.input_features`` takes them (``PolicyFeature`` fields; images
    channel-first). LeRobot 0.4.4 would otherwise make every video feature, the added streams
    included, a visual input and crash on the first batch (KeyError on ``control.motion.*``)."""
    features = info["features"]
    out = {STATE: {"type": "STATE", "shape": list(features[STATE]["shape"])}}
    for key, feature in features.items():
        if key.startswith(IMAGE_PREFIX) and feature.get("dtype") == "video":
            h, w, c = feature["shape"]
            out[key] = {"type": "VISUAL", "shape": [c, h, w]}
    return out


def lerobot_train_command(info: dict, repo_id: str, policy: str = "act") -> str:
    """The ``lerobot-train`` command that trains ``policy`` on the original cameras and the state.
    ``pretrained_backbone_weights=null``: ACT's ResNet starts from scratch, so it runs offline."""
    features = json.dumps(policy_input_features(info), separators=(", ", ": "))
    name = repo_id.rsplit("/", 1)[-1]
    args = [f"--dataset.repo_id={repo_id}", f"--policy.type={policy}",
            f"--policy.input_features={shlex.quote(features)}",
            "--policy.pretrained_backbone_weights=null", "--policy.push_to_hub=false",
            f"--output_dir=outputs/train/{policy}_{name}"]
    return " \\\n  ".join(["lerobot-train", *args])


def render_card(info: dict, repo_id: str, recipe) -> str:
    env = jinja2.Environment(undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    template = env.from_string(TEMPLATE.read_text())
    imac = imac_block(info)
    return template.render(repo_id=repo_id, recipe=recipe, info=info, imac=imac, cameras=list(imac["cameras"]),
                           lerobot_train=lerobot_train_command(info, repo_id), lerobot_version=lr.version())


def write_card(root: Path, repo_id: str, recipe) -> Path:
    info = read_info(root)
    path = root / "README.md"
    path.write_text(render_card(info, repo_id, recipe))
    return path


def hub_card_kwargs(root: Path, repo_id: str, recipe) -> dict:
    """What ``LeRobotDataset.push_to_hub`` gets for its card: our card as the dataset
    description, plus tags. LeRobot renders and uploads the card itself."""
    info = read_info(root)
    return {
        "dataset_description": render_card(info, repo_id, recipe),
        "tags": ["imac", "world-model", "robotics", f"robot:{imac_block(info)['robot']['name']}"],
        "license": "apache-2.0",
    }


def push_to_hub(root: Path, repo_id: str, recipe, *, private: bool = False) -> None:
    """Upload with LeRobot's own ``push_to_hub`` (needs a hub token and network)."""
    lr.LeRobotDataset(repo_id, root=root).push_to_hub(private=private, **hub_card_kwargs(root, repo_id, recipe))
