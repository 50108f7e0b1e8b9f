"""Issue 53's training-time white balance (``data.white_balance``, retinexgs/data/photo_balance.py): the estimate,
the balanced photo in linear light, every consumer of a view's photo seeing the same balance (targets, priors and
their cache keys), the truth untouched, and a training that says what it used."""
import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.data.photo_balance import (balance_photo, describe_photo_balance, estimate_photo_balance,
                                          grey_edge_light)
from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
from retinexgs.errors import UserError
from retinexgs.retinex.cache import prior_key, read_image
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene
from scenes import TINY_RUN, run_cli


def _photo(path, light):
    Image.fromarray((linear_to_srgb(torch.from_numpy(light)).numpy() * 255 + 0.5).astype(np.uint8)).save(path)


def _grey_scene_light(seed, h=64, w=80):
    """A grey world of blocks (every surface achromatic), so grey-edge's answer is the light's colour."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(0.05, 0.6, (h // 8, w // 8, 1))
    return np.repeat(np.repeat(blocks, 8, 0), 8, 1).repeat(3, 2)


def test_the_estimate_recovers_a_cast_of_a_grey_world_through_noise_and_8_bits(tmp_path):
    cast = np.array([1.3, 1.0, 0.7])
    rng = np.random.default_rng(0)
    paths = []
    for i in range(4):
        light = _grey_scene_light(i) * cast * 0.3 + rng.normal(0, 0.004, (64, 80, 3))  # dark and noisy
        p = tmp_path / f"{i}.png"
        _photo(p, np.clip(light, 0, 1))
        paths.append(p)
    gains = estimate_photo_balance(paths)
    assert gains[1] == 1.0
    assert gains[0] == pytest.approx(1 / 1.3, rel=0.06) and gains[2] == pytest.approx(1 / 0.7, rel=0.06)
    # without the 4×4 block means the noise's own edges pull the estimate towards grey gains
    plain = estimate_photo_balance(paths, block=1)
    assert abs(plain[2] - 1 / 0.7) > abs(gains[2] - 1 / 0.7)


def test_flat_photos_are_refused_in_one_line(tmp_path):
    p = tmp_path / "flat.png"
    _photo(p, np.full((32, 32, 3), 0.2))
    with pytest.raises(UserError, match="no edges"):
        estimate_photo_balance([p])


def test_a_balanced_photo_is_its_light_times_the_gains_clipped_or_not():
    img = torch.rand(5, 6, 3)
    g = (1.5, 1.0, 0.5)
    out = balance_photo(img, g)
    expect = linear_to_srgb((srgb_to_linear(img.double()) * torch.tensor(g, dtype=torch.float64)).clamp(0, 1))
    torch.testing.assert_close(out.double(), expect, rtol=0, atol=1e-6)
    assert balance_photo(img, None) is img
    unclipped = balance_photo(torch.full((1, 1, 3), 0.9), (2.0, 1.0, 1.0), unclipped=True)
    assert float(unclipped[0, 0, 0]) > 1.0  # a raw view keeps light above white
    assert describe_photo_balance(None).endswith("as shot") and "grey-edge" in describe_photo_balance(g)


def test_the_model_s_auto_uses_the_same_grey_edge_sums():
    from retinexgs.model.white_balance import grey_edge_gains
    imgs = [torch.rand(9, 7, 3) for _ in range(2)]
    e = grey_edge_light(imgs)
    assert grey_edge_gains(imgs) == pytest.approx((e[1] / e[0], 1.0, e[1] / e[2]))


@pytest.fixture(scope="module")
def warm(tmp_path_factory):
    from retinexgs.demo.synthetic import make_demo_scene
    return make_demo_scene(tmp_path_factory.mktemp("warm") / "scene", n_train=4, n_test=1, width=40, height=30,
                           n_points=300, color_cast=(1.4, 1.0, 0.65))


def test_every_view_but_not_the_truth_is_balanced_and_the_priors_key_follows(warm):
    cfg = load_config(["demo", "ablations/train_white_balance"])
    scene = open_scene(warm, cfg)
    plain = open_scene(warm, load_config(["demo"]))
    g = scene.train[0].balance
    assert g is not None and all(v.balance == g for v in [*scene.train, *scene.test])
    assert g[0] < 1.0 < g[2]  # a warm capture is cooled
    assert plain.train[0].balance is None
    v, u = scene.test[0], plain.test[0]
    torch.testing.assert_close(v.paired_image, u.paired_image, rtol=0, atol=0)  # the truth as it was
    torch.testing.assert_close(v.load_image().double(), balance_photo(u.load_image(), g).double(), rtol=0, atol=1e-6)
    torch.testing.assert_close(v.load_target(), v.load_image(), rtol=0, atol=0)  # a JPEG view: clipped as the photo
    p = scene.train[0].image_path
    assert prior_key(p, False, g) != prior_key(p, False, None) == prior_key(p)
    torch.testing.assert_close(read_image(p, False, g), scene.train[0].load_image(), rtol=0, atol=0)


def test_a_training_with_the_balance_says_so_and_records_it(warm, tmp_path, capsys):
    sets = [a for s in TINY_RUN for a in ("--set", s)]
    outs = {}
    for name, extra in (("shot", []), ("balanced", ["--config", "ablations/train_white_balance"])):
        code, out, err = run_cli(["train", "--data", warm, "--out", tmp_path / name, "--config", "demo", *extra,
                                  *sets, "--device", "cpu"], capsys)
        assert code == 0, err
        outs[name] = out + err
    assert "photos' white balance: grey-edge" in outs["balanced"]
    assert "photos' white balance" not in outs["shot"]
    import yaml
    assert yaml.safe_load((tmp_path / "balanced" / "config.yaml").read_text())["data"]["white_balance"] \
        == "grey-edge"
    assert yaml.safe_load((tmp_path / "shot" / "config.yaml").read_text())["data"]["white_balance"] \
        == "as-shot"


def test_the_view_store_is_keyed_by_the_balance_and_the_raw_preview():
    """The memory-mapped view store is reused for the same photo files only with the same stored values: a
    balanced run (data.white_balance) or priors from the raw preview (decomposer.raw.preview_denoise) make their own."""
    from retinexgs.train.view_store import store_tag
    plain = store_tag("lr3m-abc")
    assert plain == "lr3m-abc"
    tags = {plain, store_tag("lr3m-abc", raw_preview=True), store_tag("lr3m-abc", balance=(0.8, 1.0, 1.2)),
            store_tag("lr3m-abc", balance=(0.8, 1.0, 1.3)), store_tag("lr3m-abc", True, (0.8, 1.0, 1.2))}
    assert len(tags) == 5
    assert store_tag("lr3m-abc", balance=(0.8, 1.0, 1.2)) == store_tag("lr3m-abc", balance=[0.8, 1.0, 1.2])


def test_a_streamed_balanced_run_reads_balanced_photos_from_its_own_store(warm, tmp_path, capsys):
    """With the views streamed from the store, an as-shot run first and a balanced one after it on the same
    scene: the second must not reuse the first's store (its photos are not balanced)."""
    sets = [a for s in (*TINY_RUN, "train.stream_views=always") for a in ("--set", s)]
    for name, extra in (("a", []), ("b", ["--config", "ablations/train_white_balance"])):
        code, out, err = run_cli(["train", "--data", warm, "--out", tmp_path / name, "--config", "demo", *extra,
                                  *sets, "--device", "cpu"], capsys)
        assert code == 0, err
    stores = sorted(p.name for p in (warm / "retinex_cache").glob("views-*.bin"))
    assert any("-wb" in n for n in stores) and any("-wb" not in n for n in stores), stores
