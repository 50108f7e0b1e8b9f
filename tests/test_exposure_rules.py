"""scripts/exposure_rules.py: each rule is met exactly, and the oracle recovers a known exposure."""
import pytest
import torch

from retinexgs.model.tone import tone_map

from scenes import load_script


def load():
    return load_script("exposure_rules")


def maps(seed=0):
    g = torch.Generator().manual_seed(seed)
    R = torch.rand(24, 32, 3, generator=g, dtype=torch.float64) * 0.6 + 0.4  # every target reachable
    L = torch.rand(24, 32, 1, generator=g, dtype=torch.float64) * 0.2 + 0.02
    return R, L, torch.tensor(0.25, dtype=torch.float64)


@pytest.mark.parametrize("tone", ["exposure", "illumination"])
@pytest.mark.parametrize("stat,target", [("img_mean", 0.5), ("log_avg", 0.18), ("light_mean", 0.55),
                                         ("median", 0.46), ("lin_mean", 0.21)])
def test_solve_meets_each_rule(tone, stat, target):
    er = load()
    R, L, ref = maps()
    g = er.solve(R, L, ref, tone, stat, target)
    S, Le = tone_map(R, L, ref, torch.tensor(g, dtype=R.dtype), tone)
    assert 0.05 < g < 3.0
    assert float(er.STATS[stat](S, Le)) == pytest.approx(target, abs=2e-3)


def test_oracle_and_rule_recover_a_known_exposure():
    """Truth made by the exposure tone at g = 0.9: the matching image-mean rule scores (near) perfectly, a rule
    with a wrong target does not."""
    er = load()
    R, L, ref = maps(1)
    truth, _ = tone_map(R, L, ref, torch.tensor(0.9, dtype=R.dtype), "exposure")
    target = float(truth.mean())
    right = er.score([(R, L, truth)], ref, "exposure", lambda r, l, gt: er.solve(r, l, ref, "exposure", "img_mean",
                                                                                 target))
    wrong = er.score([(R, L, truth)], ref, "exposure", lambda r, l, gt: er.solve(r, l, ref, "exposure", "img_mean",
                                                                                 target + 0.1))
    assert right[0] > 50 and right[1] > 0.999
    assert wrong[0] < right[0] - 20
