"""`hivemap vocab train` / `info` through the real CLI (typer runner), on a tiny configuration."""

from __future__ import annotations

import cv2
import numpy as np
import skimage.data
from typer.testing import CliRunner

from hivemap.cli.main import app
from hivemap.maps.vocabulary import Vocabulary


def test_vocab_train_and_info(tmp_path) -> None:
    frames = tmp_path / "frames" / "cam0"
    frames.mkdir(parents=True)
    for i, name in enumerate(("astronaut", "rocket")):
        g = cv2.cvtColor(np.asarray(getattr(skimage.data, name)())[..., :3], cv2.COLOR_RGB2GRAY)
        cv2.imwrite(str(frames / f"{i}.png"), g)
    out = tmp_path / "v.npz"
    runner = CliRunner()
    res = runner.invoke(
        app,
        ["vocab", "train", "--out", str(out), "--images", str(tmp_path / "frames"), "--depth", "2",
         "--warps", "0", "--n-features", "300"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    v = Vocabulary.load(out)
    assert v.k == 10 and v.depth == 2 and 10 < v.num_words <= 100
    # the 18 bundled photos (no warps) + the 2 frames found recursively under --images
    assert "20 images" in res.output, res.output
    res = runner.invoke(app, ["vocab", "info", str(out)])
    assert res.exit_code == 0, res.output
    assert "words=" in res.output and "transform of 1000 descriptors" in res.output
