"""retinexgs/model/tones/: the tones as a registry. The built-in tones and their rules, the config's choices taken
from the registry, and a tone added in this module alone (registered at test time) that trains, renders and
exports through the public API."""
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.errors import UserError
from retinexgs.model.tones import TONES, IlluminationTone, Tone, get_tone, register, tone_map
from retinexgs.run.config import load_config

PACKAGE = Path(__file__).resolve().parents[1] / "retinexgs"


class ToyTone(Tone):
    """A tone no file of the package knows: the gamma on the light halved, S_enh = clip(R̂ ∘ ℓ^(g/2), 0, 1). Counts
    its calls, so a test sees that a path went through it."""

    name = "toy-half-gamma"
    formula = "R*clip(L/L_ref,0,1)^(g/2)"
    calls = 0

    def map(self, R, L, illum_ref, gamma, eps=1e-3, shoulder=1.0, noise=None, spread=None, radius=0):
        type(self).calls += 1
        light = (L / illum_ref.to(L)).clamp(0.0, 1.0).clamp_min(eps) ** (0.5 * gamma)
        return (R * light).clamp(0.0, 1.0), light


@pytest.fixture
def toy_tone():
    """ToyTone registered for one test, then removed (the registry is process-wide)."""
    register(ToyTone)
    ToyTone.calls = 0
    try:
        yield TONES[ToyTone.name]
    finally:
        TONES.pop(ToyTone.name, None)


def test_the_builtin_tones_are_registered_with_their_rules():
    assert list(TONES) == ["illumination", "signal", "exposure"]  # the order error messages name them in
    exposure, illumination, signal = (get_tone(n) for n in ("exposure", "illumination", "signal"))
    assert get_tone(exposure) is exposure and exposure.name == "exposure"
    # only the exposure tone has a linear form, a knee, a fused kernel, the meter, and needs L_ref
    assert exposure.knee(0.6) == 0.6 and illumination.knee(0.6) == 1.0 and signal.knee(0.6) == 1.0
    assert exposure.meter_applies and not illumination.meter_applies and not signal.meter_applies
    assert exposure.needs_reference and not signal.needs_reference
    assert exposure.fusable() and not illumination.fusable()
    from retinexgs.render._backend import kernels
    assert callable(getattr(kernels(), exposure.fused_kernel))
    R, L = torch.full((2, 2, 3), 0.5, dtype=torch.float64), torch.full((2, 2, 3), 0.1, dtype=torch.float64)
    ref, g = torch.tensor(0.2, dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64)
    assert exposure.linear(R, L, ref, g) is not None and illumination.linear(R, L, ref, g) is None
    torch.testing.assert_close(illumination.apply_exposure(g, 0.5, ref), g * 0.5)
    assert "R^g" in signal.describe(g, ref, 1.0, False) and "longer exposure" in exposure.describe(g, ref, 0.5, False)
    with pytest.raises(ValueError, match="tone must be one of illumination, signal, exposure, got 'filmic'"):
        get_tone("filmic")
    with pytest.raises(TypeError, match="compare tone.name"):  # a stale name check fails loudly, not silently
        bool(exposure == "exposure")


def test_register_refuses_a_second_tone_under_a_taken_name():
    class Another(IlluminationTone):
        name = "illumination"

    with pytest.raises(ValueError, match="already registered"):
        register(Another)
    assert type(TONES["illumination"]) is IlluminationTone

    class Nameless(Tone):
        pass

    with pytest.raises(ValueError, match="non-empty string `name`"):
        register(Nameless)


def test_the_configs_tone_choices_are_the_registrys(toy_tone):
    with pytest.raises(UserError, match=r"--set model.enhancement.tone=filmic: model.enhancement.tone must be one "
                                        r"of illumination, signal, exposure, toy-half-gamma, got 'filmic'$"):
        load_config([], ["model.enhancement.tone=filmic"])
    assert load_config([], [f"model.enhancement.tone={toy_tone.name}"]).model.enhancement.tone == toy_tone.name
    # the rules a tone sets, from its attributes: the toy needs no reference
    with pytest.raises(UserError, match="tone 'exposure' needs a ref_quantile.*only valid with 'illumination' or "
                                        "'signal' or 'toy-half-gamma'"):
        load_config([], ["model.enhancement.ref_quantile=null", "loss.rec_domain=photo"])
    load_config([], [f"model.enhancement.tone={toy_tone.name}", "model.enhancement.ref_quantile=null",
                     "loss.rec_domain=photo"])
    TONES.pop(toy_tone.name)
    with pytest.raises(UserError, match="must be one of illumination, signal, exposure, got 'toy-half-gamma'"):
        load_config([], [f"model.enhancement.tone={toy_tone.name}"])


def test_a_tone_added_in_one_file_trains_renders_and_exports(tmp_path, toy_tone):
    from retinexgs.cli import main
    from retinexgs.run.folder import load_run
    from retinexgs.run.render import view_camera
    from scenes import TINY_RUN, tiny_trained_run

    _, run = tiny_trained_run(tmp_path, TINY_RUN + ["loss.enhance_from=1", f"model.enhancement.tone={toy_tone.name}"],
                              n_test=1, width=24, height=18)
    assert ToyTone.calls > 0  # training toned through it (the enhancement loss)
    cfg, scene, model, step = load_run(run, "cpu")
    assert model.tone is toy_tone and cfg.model.enhancement.tone == toy_tone.name
    cam = view_camera(scene.test[0])
    with torch.no_grad():
        res = model.render(cam, 1)
        ell = (res["L"] / model.illum_ref).clamp(0, 1).clamp_min(model.enhancement.eps)
        want = (res["R"] * ell ** (0.5 * res["gamma"].reshape(-1))).clamp(0, 1)
    torch.testing.assert_close(res["rgb"], want, rtol=0, atol=1e-6)
    assert float((res["rgb"] - tone_map(res["R"], res["L"], model.illum_ref, res["gamma"].reshape(-1),
                                        "illumination")[0]).abs().max()) > 1e-3  # not the paper's tone in disguise

    cli = lambda *a: main([*map(str, a), "--device", "cpu", "--quiet"])  # noqa: E731
    means = {}
    for exposure in ("0.5", "1"):  # the base class's exposure rule: g times X, brighter below 1
        calls = ToyTone.calls
        assert cli("render", "--run", run, "--out", tmp_path / exposure, "--exposure", exposure) == 0
        assert ToyTone.calls > calls
        png, = sorted((tmp_path / exposure / "enhanced").glob("*.png"))  # the one test view
        means[exposure] = np.mean(np.asarray(Image.open(png), float))
    assert means["0.5"] > means["1"] > 0, means
    assert cli("export", "--run", run, "--out", tmp_path / "toy.ply") == 0
    header = (tmp_path / "toy.ply").read_bytes()[:8192].decode("latin-1")
    assert "colour: enhanced R*clip(L/L_ref,0,1)^(g/2), L_ref = " in header

    # a run of a tone that is no longer registered: one line naming it, not a traceback
    TONES.pop(toy_tone.name)
    with pytest.raises(UserError, match="model.enhancement.tone must be one of .*got 'toy-half-gamma'"):
        load_run(run, "cpu")


def test_no_tone_is_checked_by_name_outside_the_tones_package():
    """A new tone must not need edits elsewhere: no ``tone == "exposure"``-style comparison outside model/tones/."""
    check = re.compile(r"""tone(\.name)?\s*(==|!=|\bnot in\b|\bin\b)\s*[("'\[]""")
    found = []
    for path in PACKAGE.rglob("*.py"):
        if (PACKAGE / "model" / "tones") in path.parents:
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if check.search(line.split("#")[0]):
                found.append(f"{path.relative_to(PACKAGE)}:{n}: {line.strip()}")
    assert not found, found
