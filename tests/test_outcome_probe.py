"""The outcome probe (benchmarks/outcome_probe.py) against planted answers: it reads a label that a
2-pixel shift of a small square decides, and stays near chance where the label is noise."""

import torch

from benchmarks.outcome_probe import fit_predict
from imac_model.evaluate.success import verdict_scores


def _squares(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` 6x24x32 frames, each a 4-pixel square at a random place; the label is whether it sits
    2 px right of where a second, fixed-offset square says it should (a grasp's offset, in small)."""
    g = torch.Generator().manual_seed(seed)
    images = torch.zeros(n, 6, 24, 32)
    label = torch.rand(n, generator=g) < 0.5
    for i in range(n):
        y, x = int(torch.randint(4, 16, (1,), generator=g)), int(torch.randint(4, 20, (1,), generator=g))
        images[i, 0, y:y + 4, x:x + 4] = 1.0  # the reference (the cube)
        dx = 2 if label[i] else 0
        images[i, 1, y:y + 4, x + 4 + dx:x + 8 + dx] = 1.0  # the control (the fingers)
    return images, label


def _out_of_fold(images: torch.Tensor, label: torch.Tensor, folds: int = 3) -> float:
    fold = torch.arange(len(label)) % folds
    logits = torch.empty(len(label))
    for f in range(folds):
        tr, te = fold != f, fold == f
        logits[te] = fit_predict((images[tr], None), label[tr], (images[te], None), steps=150, seed=f)
    return verdict_scores((logits > 0).tolist(), label.tolist())["balanced_accuracy"]


def test_the_probe_reads_a_planted_offset_and_not_noise():
    torch.set_num_threads(1)
    images, label = _squares(192, seed=0)
    assert _out_of_fold(images, label) > 0.9
    shuffled = label[torch.randperm(len(label), generator=torch.Generator().manual_seed(1))]
    assert 0.3 < _out_of_fold(images, shuffled) < 0.7
