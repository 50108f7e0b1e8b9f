"""The benchmark command lines' shared image-size argument: the pair in the order written, one-line errors."""
import argparse

import pytest

from retinexgs.bench.args import image_size


def test_pair_in_the_order_written():
    assert image_size("HxW", "3000x4000")("3000x4000") == (3000, 4000)
    assert image_size("WxH", "640x480")("640X480") == (640, 480)


@pytest.mark.parametrize("text, match", [("640", "expected WxH, e.g. 640x480, got '640'"),
                                         ("ax3", "expected WxH"), ("1x2x3", "expected WxH"),
                                         ("7x480", "at least 8x8 is needed, got '7x480'")])
def test_bad_sizes_are_argparse_errors(text, match):
    with pytest.raises(argparse.ArgumentTypeError, match=match):
        image_size("WxH", "640x480")(text)


def test_minimum_and_the_command_line(capsys):
    with pytest.raises(argparse.ArgumentTypeError, match="at least 32x32"):
        image_size("HxW", "3000x4000", minimum=32)("31x4000")
    ap = argparse.ArgumentParser(prog="bench")
    ap.add_argument("--size", type=image_size("HxW", "3000x4000"))
    with pytest.raises(SystemExit):
        ap.parse_args(["--size", "big"])
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "bench: error: argument --size: expected HxW, e.g. 3000x4000, got 'big'"
