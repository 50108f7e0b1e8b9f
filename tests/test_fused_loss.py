"""The fused supervision pass (retinexgs/train/fused_loss.py, csrc/include/rgs/supervision.h): the CPU kernel against
its pure-torch twins (supervision_loss, tv_loss, depth_smoothness_loss) in float64, values and gradients, for every
reconstruction form it covers, with and without the depth prior; its own finite differences; the configurations it
declines; and the objective's graphed loss through it against the same loss through the twins."""
import pytest
import torch

from retinexgs.train import losses
from retinexgs.train.fused_loss import REC_FORMS, _SupervisionPass, plan, supervision_terms
from retinexgs.train.losses import LinearTarget, to_bchw
from retinexgs.train.views import pad_edges
from scenes import needs_cuda

H, W = 13, 17
WEIGHTS = (0.5, 0.5, 1.0)


def scene(depth: bool, seed: int = 0, dtype=torch.float64, raw: bool = False):
    """A render [H,W,6|8] and packed targets [H,W,7|9] with no exact ties (the L1 terms' kinks)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    R_hat, L_hat = 0.05 + 0.9 * r(H, W, 3), 0.02 + 0.5 * r(H, W, 3)
    S = 0.3 * r(H, W, 3) - (0.05 if raw else 0.0)  # a raw view's noise goes below black
    R, L = r(H, W, 3), 0.4 * r(H, W, 1)
    maps = [R_hat, L_hat]
    packed = [S, R, L]
    if depth:
        # alpha away from the coverage threshold (0.5), where the mask jumps
        alpha = torch.where(r(H, W, 1) < 0.2, 0.1 + 0.3 * r(H, W, 1), 0.6 + 0.4 * r(H, W, 1))
        maps += [1.0 + 3.0 * r(H, W, 1), alpha]
        packed.append(pad_edges(*losses.edge_weights(to_bchw(R), 10.0)))
    return torch.cat(maps, -1), torch.cat(packed, -1)


def twin(image, packed, lambda_ssim, gain, l1_exposed, linear, r_luma=1.0):
    """The torch terms the pass replaces, as RetinexObjective computes them."""
    R_hat, L_hat = to_bchw(image[..., :3]), to_bchw(image[..., 3:6])
    S, R, L = (to_bchw(packed[..., a:b]) for a, b in ((0, 3), (3, 6), (6, 7)))
    total, terms = losses.supervision_loss(R_hat, L_hat, R, L, S, *WEIGHTS, lambda_ssim, gain, l1_exposed, linear,
                                           r_luma)
    terms["tv"] = losses.tv_loss(R_hat)
    if image.shape[-1] == 8:
        wx, wy = packed[None, None, :, :-1, -2], packed[None, None, :-1, :, -1]
        terms["depth"] = losses.depth_smoothness_loss(to_bchw(image[..., 6:7]), to_bchw(image[..., 7:8]), wx, wy)
    return total, terms


def linear_target(mode, prior_snr, gain):
    a = torch.tensor([2e-3, 1.5e-3, 3e-3], dtype=torch.float64).reshape(1, 3, 1, 1)
    b = torch.tensor([1e-5, 2e-5, 1.5e-5], dtype=torch.float64).reshape(1, 3, 1, 1)
    return LinearTarget(mode, a, b, gain=gain, prior_snr=prior_snr)


GAIN = torch.tensor(4.0, dtype=torch.float64)
CASES = {  # name: (gain, l1_exposed, linear)
    "photo-domain": (None, True, None),
    "exposed-ssim": (GAIN, False, None),
    "exposed-l1": (GAIN, True, None),
    "raw-noise-prior-snr": (GAIN * 0.5, False, linear_target("noise", 3.0, GAIN)),
    "raw-relative": (GAIN, False, linear_target("relative", 0.0, None)),
    "raw-noise-no-ssim-gain": (None, False, linear_target("noise", 0.0, GAIN)),
}


def run_both(case, depth, lambda_ssim, seed=0, r_luma=1.0):
    gain, l1_exposed, linear = CASES[case]
    image, packed = scene(depth, seed, raw=linear is not None)
    sup = plan(gain, l1_exposed, linear, image, r_luma)
    assert sup is not None and sup.r_luma == r_luma
    out = []
    for fn in (lambda x: supervision_terms(x, packed, sup, WEIGHTS, lambda_ssim, linear),
               lambda x: twin(x, packed, lambda_ssim, gain, l1_exposed, linear, r_luma)):
        x = image.clone().requires_grad_(True)
        total, terms = fn(x)
        # one combination of every term, each with its own weight, so that each term's gradient counts
        combo = total + sum((i + 2.0) * t for i, t in enumerate(terms.values()))
        out.append((total.detach(), {k: v.detach() for k, v in terms.items()}, torch.autograd.grad(combo, x)[0]))
    return out


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("depth", [False, True])
# loss.raw.r_prior_luma: the paper's R prior, its chroma alone, between
@pytest.mark.parametrize("r_luma", [1.0, 0.0, 0.3])
def test_pass_matches_the_torch_terms(case, depth, r_luma):
    (total, terms, grad), (total_t, terms_t, grad_t) = run_both(case, depth, 0.2, r_luma=r_luma)
    assert list(terms) == list(terms_t)
    torch.testing.assert_close(total, total_t, rtol=1e-10, atol=1e-12)
    for name in terms:
        torch.testing.assert_close(terms[name], terms_t[name], rtol=1e-10, atol=1e-12, msg=name)
    torch.testing.assert_close(grad, grad_t, rtol=1e-8, atol=1e-12)
    assert grad.abs().sum() > 0


def test_pass_without_ssim_matches():
    (total, terms, grad), (total_t, terms_t, grad_t) = run_both("exposed-l1", True, 0.0)
    torch.testing.assert_close(total, total_t, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grad, grad_t, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("case,r_luma", [("exposed-l1", 1.0), ("raw-noise-prior-snr", 1.0), ("exposed-l1", 0.3)])
def test_pass_finite_differences(case, r_luma):
    """torch.autograd.gradcheck of the pass itself: every output (x9 and the sums) against float64 differences."""
    gain, l1_exposed, linear = CASES[case]
    image, packed = scene(True, 3, raw=linear is not None)
    image, packed = image[:6, :7].contiguous(), packed[:6, :7].contiguous()
    sup = plan(gain, l1_exposed, linear, image, r_luma)

    def fn(x):
        x9, _, sums = _SupervisionPass.apply(x, packed, None, sup)
        # Σw and the counts have no gradient by definition; nor, on a raw scene, has the linear term's weight w,
        # which the twin takes under no_grad (its gradient is held to the twin's above, not to differences)
        skip = (3, 7, 9, 11) + ((2,) if linear is not None else ())
        keep = [i for i in range(12) if i not in skip]
        return x9, sums[keep]

    assert torch.autograd.gradcheck(fn, (image.clone().requires_grad_(True),), eps=1e-7, atol=1e-6)


def test_plan_declines_what_it_does_not_cover():
    image, _ = scene(False)
    sigma = linear_target("noise", 0.0, GAIN)._replace(unit="sigma")
    assert plan(GAIN, False, sigma, image) is None
    assert plan(GAIN.clone().requires_grad_(True), False, None, image) is None
    assert plan(GAIN, True, None, image).rec_form == REC_FORMS["exposed"]
    assert plan(None, True, None, image).rec_form == REC_FORMS["plain"]


def test_kernel_rejects_bad_shapes():
    from retinexgs.render._backend import kernels
    image, packed = scene(False)
    with pytest.raises(ValueError, match="image must be"):
        kernels().supervision_forward(image[..., :5], packed, None, None, None, None, None, 0, 1, 1e-3, 0.5, 1e-6, 1.0)
    with pytest.raises(ValueError, match="packed"):
        kernels().supervision_forward(image, packed[..., :6], None, None, None, None, None, 0, 1, 1e-3, 0.5, 1e-6, 1.0)
    with pytest.raises(ValueError, match="needs lin_gain"):
        kernels().supervision_forward(image, packed, None, None, None, None, None, 1, 1, 1e-3, 0.5, 1e-6, 1.0)
    with pytest.raises(ValueError, match="r_luma must be in"):
        kernels().supervision_forward(image, packed, None, None, None, None, None, 0, 1, 1e-3, 0.5, 1e-6, 1.5)


def test_float32_close_to_float64():
    image, packed = scene(True, 5)
    sup64 = plan(GAIN, False, None, image)
    t64, terms64 = supervision_terms(image, packed, sup64, WEIGHTS, 0.2)
    image32, packed32 = image.float(), packed.float()
    t32, terms32 = supervision_terms(image32, packed32, plan(GAIN.float(), False, None, image32), WEIGHTS, 0.2)
    for name in terms64:
        torch.testing.assert_close(terms32[name].double(), terms64[name], rtol=1e-5, atol=1e-6, msg=name)


@needs_cuda
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("r_luma", [1.0, 0.0])
def test_cuda_pass_matches_cpu(case, dtype, r_luma):
    """The CUDA kernels against the CPU ones (the reference): terms and gradients, on a view larger than a block."""
    gain, l1_exposed, linear = CASES[case]
    g = torch.Generator().manual_seed(11)
    image, packed = scene(True, 11, dtype=dtype, raw=linear is not None)
    image = image.repeat(5, 7, 1)  # 65 x 119: many blocks, edges inside them
    packed = packed.repeat(5, 7, 1)
    out = {}
    weights = torch.rand(5, generator=g, dtype=dtype) + 0.5  # one draw for both devices
    for device in ("cpu", "cuda"):
        lin = None if linear is None else linear._replace(
            a=linear.a.to(device, dtype), b=linear.b.to(device, dtype),
            gain=None if linear.gain is None else linear.gain.to(device, dtype))
        gn = None if gain is None else gain.to(device, dtype)
        x = image.to(device).requires_grad_(True)
        p = packed.to(device)
        total, terms = supervision_terms(x, p, plan(gn, l1_exposed, lin, x, r_luma), WEIGHTS, 0.2, lin)
        w = weights[:len(terms)].to(device)
        combo = total + (torch.stack(list(terms.values())) * w).sum()
        out[device] = ([float(t) for t in terms.values()], torch.autograd.grad(combo, x)[0].cpu())
    tol = dict(rtol=1e-9, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-4, atol=1e-6)
    for a, b in zip(out["cpu"][0], out["cuda"][0]):
        assert b == pytest.approx(a, rel=tol["rtol"], abs=tol["atol"])
    torch.testing.assert_close(out["cuda"][1], out["cpu"][1], rtol=tol["rtol"] * 10, atol=tol["atol"] * 10)
