"""bench.solid: the share of the pixels an avatar covers that it covers opaquely, from every side."""

from __future__ import annotations

import math

import torch

from rmavatar.avatar import load_trained
from rmavatar.bench.solid import solidity


def test_a_ghost_is_less_solid_than_the_avatar(trained_run):
    """The tiny trained avatar, then the same with every opacity shrunk to a third (a ghost): the share of
    opaque pixels and the mean alpha fall; the numbers are shares, per view as in all."""
    trained = load_trained(trained_run)
    solid = solidity(trained, views=4, size=64)
    assert solid["views"] == 4 and len(solid["per_view"]) == 4
    assert 0.0 <= solid["opaque_share"] <= 1.0 and 0.1 < solid["mean_alpha"] <= 1.0
    assert math.isclose(sum(solid["per_view"]) / 4, solid["opaque_share"], abs_tol=0.15)
    with torch.no_grad():
        p = torch.sigmoid(trained.avatar.opacity_logits) / 3
        trained.avatar.opacity_logits.copy_(torch.log(p / (1 - p)))
    ghost = solidity(trained, views=4, size=64)
    assert ghost["mean_alpha"] < solid["mean_alpha"] - 0.05
    assert solid["opaque_share"] > 0.3 and ghost["opaque_share"] < 0.5 * solid["opaque_share"]
