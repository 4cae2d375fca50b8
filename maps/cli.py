"""`hivemap vocab` sub-commands (owned by the maps package): train and inspect the ORB vocabulary.

The vocabulary is hand-written (``hivemap.maps.vocabulary``) because no maintained Python DBoW
package installs here (DESIGN.md). Training data: scikit-image's bundled photos, each warped by random
homographies (viewpoint, scale, rotation changes: every warp is one document for the idf), plus
rendered frames from ``--images`` folders (``*.png`` found recursively, e.g. a rendered dataset folder).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

vocab_app = typer.Typer(no_args_is_help=True, help="Train and inspect the ORB bag-of-words vocabulary.")

SKIMAGE_PHOTOS = (
    "astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins", "grass", "gravel",
    "horse", "hubble_deep_field", "immunohistochemistry", "moon", "page", "retina", "rocket", "text",
)  # fmt: skip


def _gray(img: Any) -> Any:
    import cv2
    import numpy as np

    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        img = (255 * (img - img.min()) / max(float(img.max() - img.min()), 1e-9)).astype(np.uint8)
    return img


def _extractor(n_features: int) -> Any:
    """ORB extractor: the project's (``hivemap.maps.features``) when present, else OpenCV's directly."""
    try:
        from hivemap.maps.features import OrbOptions, extract_orb

        opts = OrbOptions(n_features=n_features)
        return lambda g: extract_orb(g, opts)[2]
    except ImportError:
        import cv2

        orb = cv2.ORB_create(  # type: ignore[attr-defined]
            nfeatures=n_features, scaleFactor=1.2, nlevels=8, fastThreshold=20
        )

        def run(g: Any) -> Any:
            _, d = orb.detectAndCompute(g, None)
            return d

        return run


def _random_homography(w: int, h: int, rng: Any) -> Any:
    import cv2
    import numpy as np

    src = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
    jitter = rng.uniform(-0.2, 0.2, size=(4, 2)) * [w, h]
    dst = (src + jitter).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    ang = rng.uniform(-np.pi, np.pi) * 0.3
    sc = rng.uniform(0.6, 1.5)
    c, s = np.cos(ang) * sc, np.sin(ang) * sc
    A = np.array([[c, -s, w / 2 - c * w / 2 + s * h / 2], [s, c, h / 2 - s * w / 2 - c * h / 2], [0, 0, 1]])
    return A @ H


def training_images(image_dirs: list[Path], warps_per_photo: int, max_images: int, seed: int) -> list[Any]:
    """Grayscale training images: warped scikit-image photos + up to ``max_images`` rendered frames."""
    import cv2
    import numpy as np
    import skimage.data

    rng = np.random.default_rng(seed)
    out = []
    for name in SKIMAGE_PHOTOS:
        try:
            g = _gray(getattr(skimage.data, name)())
        except Exception:  # some photos need the optional pooch download
            continue
        h, w = g.shape
        out.append(g)
        for _ in range(warps_per_photo):
            H = _random_homography(w, h, rng)
            out.append(cv2.warpPerspective(g, H, (w, h), borderMode=cv2.BORDER_REFLECT))
    files: list[Path] = []
    for d in image_dirs:
        files.extend(sorted(Path(d).rglob("*.png")))
    if len(files) > max_images:
        pick = rng.choice(len(files), size=max_images, replace=False)
        files = [files[i] for i in sorted(pick)]
    for f in files:
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if g is not None:
            out.append(g)
    return out


@vocab_app.command("train")
def train(
    out: Annotated[Path, typer.Option(help="output .npz")] = Path("maps/data/orb_vocab.npz"),
    images: Annotated[list[Path] | None, typer.Option(help="folders of rendered frames (*.png)")] = None,
    k: Annotated[int, typer.Option(help="branching factor")] = 10,
    depth: Annotated[int, typer.Option(help="tree depth (words <= k^depth)")] = 4,
    warps: Annotated[int, typer.Option(help="homography warps per scikit-image photo")] = 6,
    max_images: Annotated[int, typer.Option(help="max rendered frames used")] = 400,
    n_features: Annotated[int, typer.Option(help="ORB features per image")] = 1000,
    seed: int = 0,
) -> None:
    """Train a vocabulary on scikit-image photos (+ rendered frames) and write it as .npz."""
    import time

    from hivemap.maps.vocabulary import TrainOptions, Vocabulary

    t0 = time.perf_counter()
    imgs = training_images(list(images or []), warps, max_images, seed)
    extract = _extractor(n_features)
    descs = [d for d in (extract(g) for g in imgs) if d is not None and len(d)]
    n_desc = sum(len(d) for d in descs)
    typer.echo(f"{len(descs)} images, {n_desc} descriptors ({time.perf_counter() - t0:.1f} s)")
    vocab = Vocabulary.train(descs, TrainOptions(k=k, depth=depth, seed=seed), progress=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    vocab.save(out)
    typer.echo(f"{vocab} -> {out} ({out.stat().st_size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s)")


@vocab_app.command("info")
def info(
    path: Annotated[Path | None, typer.Argument(help="vocabulary .npz (default: the shipped one)")] = None,
) -> None:
    """Print a vocabulary's size, shape and transform speed."""
    import time

    import numpy as np

    from hivemap.maps.vocabulary import Vocabulary, default_vocabulary

    vocab = Vocabulary.load(path) if path else default_vocabulary()
    typer.echo(str(vocab))
    depth_hist = np.bincount(vocab.level[vocab.word_of_node >= 0], minlength=vocab.depth + 1)
    typer.echo(f"words per level: {depth_hist.tolist()}")
    typer.echo(f"idf range {vocab.idf.min():.2f}..{vocab.idf.max():.2f}")
    d = np.random.default_rng(0).integers(0, 256, size=(1000, 32), dtype=np.uint8)
    vocab.transform(d)
    t = time.perf_counter()
    for _ in range(20):
        vocab.transform(d)
    typer.echo(f"transform of 1000 descriptors: {(time.perf_counter() - t) / 20 * 1e3:.2f} ms")
