"""The scene constants derived from L_ref (retinexgs/model/tones/exposure.py): log lin(L_ref) and the gain at g = 1
computed once per reference tensor and reused, recomputed when the buffer changes in place, never cached for a
reference with a gradient, and looked up without comparing tensors (a tensor's == is elementwise: a sync on the GPU)."""
import torch

from retinexgs.data.srgb import srgb_to_linear
from retinexgs.model.tones.exposure import exposure_gain, log_lin_ref, reference_gain


def _fresh(ref, like):
    return torch.log(srgb_to_linear(ref.to(like)).clamp_min(1e-6)).clamp_max(-1e-6)


def test_cached_value_is_the_computed_one_and_reused():
    ref = torch.tensor(0.3)
    like = torch.ones((), dtype=torch.float64)
    a = log_lin_ref(ref, like)
    assert a.dtype == torch.float64 and torch.equal(a, _fresh(ref, like))
    assert log_lin_ref(ref, like) is a  # reused, not recomputed
    assert log_lin_ref(ref, torch.ones(())) is not a  # another dtype: its own value
    g = reference_gain(ref)
    assert torch.equal(g, torch.exp((-_fresh(ref, ref) / 1.0).clamp_max(40.0)))
    assert reference_gain(ref) is g
    assert torch.equal(g, exposure_gain(ref, ref.new_ones(()), _fresh(ref, ref)))


def test_in_place_change_recomputes():
    ref = torch.tensor(0.3)
    before = reference_gain(ref)
    ref.fill_(0.6)  # what initialise_levels / load_state_dict do to the buffer
    after = reference_gain(ref)
    assert after is not before and torch.equal(after, exposure_gain(ref, ref.new_ones(()), _fresh(ref, ref)))
    assert float(after) < float(before)  # a brighter scene needs less gain


def test_two_references_do_not_share():
    a, b = torch.tensor(0.2), torch.tensor(0.5)
    assert float(reference_gain(a)) != float(reference_gain(b))


def test_reference_with_gradient_is_not_cached():
    ref = torch.tensor(0.3, requires_grad=True)
    like = torch.ones(())
    x, y = log_lin_ref(ref, like), log_lin_ref(ref, like)
    assert x is not y and x.requires_grad
    x.backward()
    assert ref.grad is not None and float(ref.grad) != 0.0


def test_lookup_compares_no_tensors(monkeypatch):
    ref = torch.tensor(0.3)
    reference_gain(ref)

    def refuse(self, other):
        raise AssertionError("a tensor was compared")

    monkeypatch.setattr(torch.Tensor, "__eq__", refuse)
    reference_gain(ref)
    log_lin_ref(ref, ref)
