"""The dataset card (README.md of a built dataset), rendered from ``dataset_cards/``.

The same text goes to the hub: ``push_to_hub`` passes it to LeRobot's own card as its
``dataset_description``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jinja2

TEMPLATE = Path(__file__).resolve().parent.parent / "dataset_cards" / "imac_dataset_card.md"


def render_card(info: dict, repo_id: str, recipe) -> str:
    env = jinja2.Environment(undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    template = env.from_string(TEMPLATE.read_text())
    imac = info["imac"]
    return template.render(repo_id=repo_id, recipe=recipe, info=info, imac=imac, cameras=list(imac["cameras"]))


def write_card(root: Path, repo_id: str, recipe) -> Path:
    info = json.loads((root / "meta" / "info.json").read_text())
    path = root / "README.md"
    path.write_text(render_card(info, repo_id, recipe))
    return path
