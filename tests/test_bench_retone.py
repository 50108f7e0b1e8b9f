"""python -m retinexgs.bench retone: only the enhancement is re-trained, only enhancement keys may change."""
import pytest
import torch

from retinexgs.train.benchmarks import retone
from retinexgs.errors import UserError
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, view_camera

from scenes import TINY_RUN, tiny_trained_run


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    return tiny_trained_run(tmp_path_factory.mktemp("retone"), TINY_RUN + ["loss.enhance_from=1"])


def test_variant_config_takes_enhancement_keys_and_refuses_the_rest(trained):
    _, run = trained
    cfg, *_ = load_run(run)
    old = retone.variant_config(cfg, "ablations/tone_illumination")
    assert old.model.enhancement.tone == "illumination" and old.steps == cfg.steps
    assert retone.variant_config(cfg, "ablations/exp_on_illumination").loss.exp_on == "illumination"
    assert retone.variant_config(cfg, "ablations/with_col").loss.w_col == 0.5
    assert retone.variant_config(cfg, "default") == cfg
    with pytest.raises(UserError, match="model.sh_degree"):
        retone.variant_config(cfg, "ablations/reflectance_sh0")
    with pytest.raises(UserError, match="ref_quantile"):
        retone.variant_config(cfg, "ablations/ref_p99")


def test_retone_trains_the_enhancement_alone_and_scores_every_config(trained, capsys):
    _, run = trained
    cfg, scene, model, step = load_run(run)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    degree = active_sh_degree(cfg, step)
    with torch.no_grad():
        maps = []
        for v in scene.train:
            res = model.render(view_camera(v), degree, enhance=False)
            maps.append((res["R"], res["L"], v.image.to(res["R"])))
    m = retone.retone(model, retone.variant_config(cfg, "ablations/tone_illumination"), maps, steps=3)
    assert m.tone.name == "illumination" and model.tone.name == "exposure"
    assert m.gaussians is model.gaussians and m.enhancement is not model.enhancement
    for k, v in model.state_dict().items():  # the run's model is untouched (its net too)
        assert torch.equal(v, before[k]), k
    # The new net moved from its initial gamma (0.45 for tone illumination) under L_enhance.
    g = m.enhance(maps[0][0], maps[0][1])["gamma"].detach()
    assert torch.isfinite(g).all() and float(g.mean()) != pytest.approx(0.45, abs=1e-7)
    md = retone.run([run], ["default", "ablations/exp_on_illumination"], steps=2, device="cpu", seeds=[0, 1])
    rows = md.splitlines()[2:]
    assert len(rows) == 3 and "`ablations/exp_on_illumination`" in rows[-1] and "(the run's own" in rows[0]
    assert " ± " in rows[-1]
    assert retone.main(["--runs", str(run), "--configs", "ablations/reflectance_sh0", "--steps", "1"]) == 2
    assert "only the enhancement" in capsys.readouterr().err
