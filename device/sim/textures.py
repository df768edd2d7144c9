"""Procedural 8-bit grey textures for the simulated scene (no image files, no copyrighted content).

Every texture is a pure function of ``(seed, size, style)``: multi-scale value noise (a
pink-ish spectrum from cells of 256 down to 2 texels), random filled and outlined shapes,
lines of pseudo-words printed with ``cv2.putText`` and a little texel-level grain.  That
mix gives SIFT many well-localised, distinctive keypoints at every scale while staying
free of long repetitive structures that would make matching ambiguous.

Styles (``STYLES``):

* ``"wall"``   – soft blotchy paint with posters/notes (shapes + text blocks);
* ``"floor"``  – higher-contrast speckled noise with tiles of scattered marks;
* ``"wood"``   – streaky grain stretched along the texture's x axis, a few knots;
* ``"box"``    – cardboard-like noise with printed labels, logos and text;
* ``"book"``   – a cover: frame, big title, lines of small print, emblem.

A texture is finally blurred by ``sigma = 0.5`` texel so that drawn edges are band-limited
(the renderer samples it bilinearly and with mip-maps).
"""

from __future__ import annotations

import cv2
import numpy as np

STYLES = ("wall", "floor", "wood", "box", "book")

_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_COMPLEX_SMALL,
)
_CONSONANTS = "bcdfghjklmnprstvwxz"
_VOWELS = "aeiouy"


def _rng(seed: int, *keys: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *[int(k) & 0xFFFFFFFF for k in keys]])


def pseudo_word(rng: np.random.Generator) -> str:
    """A pronounceable random word (1-3 syllables), sometimes capitalised or with digits."""
    n = int(rng.integers(1, 4))
    ci = rng.integers(0, len(_CONSONANTS), n + 1)
    vi = rng.integers(0, len(_VOWELS), n)
    w = "".join(_CONSONANTS[c] + _VOWELS[v] for c, v in zip(ci[:n], vi))
    r = rng.random(4)
    if r[0] < 0.4:
        w += _CONSONANTS[ci[n]]
    if r[1] < 0.25:
        w = w.upper()
    elif r[1] < 0.6:
        w = w.capitalize()
    if r[2] < 0.15:
        w += str(int(r[3] * 1000))
    return w


def value_noise(rng: np.random.Generator, shape: tuple[int, int], coarsest: int = 256, finest: int = 2,
                beta: float = 0.7, stretch: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Multi-scale noise with zero mean and unit std, built as a Laplacian-like pyramid.

    Starting from a random grid with cells of ``coarsest`` texels, the field is upsampled by two
    (``cv2.pyrUp``) and fresh white noise of amplitude ``cell ** beta`` is added at every scale
    down to cells of ``finest`` texels.  ``stretch = (sx, sy)`` elongates all features (wood grain
    along x for ``sx > 1``).
    """
    h, w = shape
    gh = max(1, int(np.ceil(h / stretch[1])))
    gw = max(1, int(np.ceil(w / stretch[0])))
    levels = max(0, int(round(np.log2(max(coarsest, 1)))))
    fine = max(0, int(round(np.log2(max(finest, 1)))))
    field = None
    for lev in range(levels, fine - 1, -1):
        c = 2 ** lev
        sh = (int(np.ceil(gh / c)) + 2, int(np.ceil(gw / c)) + 2)
        layer = rng.standard_normal(sh).astype(np.float32) * float(c) ** beta
        if field is None:
            field = layer
        else:
            up = cv2.pyrUp(field)
            field = up[:sh[0], :sh[1]] + layer
    if fine > 0:
        for _ in range(fine):
            field = cv2.pyrUp(field)
    field = field[:gh, :gw]
    if (gh, gw) != (h, w):
        field = cv2.resize(field, (w, h), interpolation=cv2.INTER_LINEAR)
    field = field - field.mean()
    s = float(field.std())
    return field / s if s > 0 else field


def _grey(rng: np.random.Generator, lo: int = 10, hi: int = 245) -> int:
    return int(rng.integers(lo, hi))


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, count: int, size_range: tuple[float, float]) -> None:
    h, w = img.shape
    for _ in range(count):
        kind = int(rng.integers(0, 6))
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = float(np.exp(rng.uniform(np.log(size_range[0]), np.log(size_range[1]))))
        col = _grey(rng)
        thick = -1 if rng.random() < 0.6 else int(rng.integers(1, max(2, int(s / 8) + 2)))
        if kind == 0:
            cv2.circle(img, (cx, cy), max(1, int(s / 2)), col, thick, cv2.LINE_AA)
        elif kind == 1:
            a = float(rng.uniform(0, 180))
            cv2.ellipse(img, (cx, cy), (max(1, int(s / 2)), max(1, int(s * rng.uniform(0.15, 0.5)))), a, 0, 360, col, thick,
                        cv2.LINE_AA)
        elif kind == 2:
            wx, wy = s * rng.uniform(0.4, 1.0), s * rng.uniform(0.4, 1.0)
            cv2.rectangle(img, (int(cx - wx / 2), int(cy - wy / 2)), (int(cx + wx / 2), int(cy + wy / 2)), col, thick,
                          cv2.LINE_AA)
        elif kind == 3:
            n = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = s / 2 * rng.uniform(0.4, 1.0, n)
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)
            if thick < 0:
                cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
            else:
                cv2.polylines(img, [pts], True, col, thick, cv2.LINE_AA)
        elif kind == 4:
            a = rng.uniform(0, np.pi)
            dx, dy = s / 2 * np.cos(a), s / 2 * np.sin(a)
            cv2.line(img, (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy)), col, max(1, int(s / 20)), cv2.LINE_AA)
        else:  # a small checker/crosshair marker
            r = max(2, int(s / 4))
            cv2.rectangle(img, (cx - r, cy - r), (cx, cy), col, -1)
            cv2.rectangle(img, (cx, cy), (cx + r, cy + r), col, -1)
            cv2.rectangle(img, (cx - r, cy), (cx, cy + r), 255 - col, -1)
            cv2.rectangle(img, (cx, cy - r), (cx + r, cy), 255 - col, -1)


def _draw_text_block(img: np.ndarray, rng: np.random.Generator, x: int, y: int, width: int, line_h: float,
                     lines: int, col: int) -> None:
    """Lines of pseudo-words starting at (x, y) (baseline), wrapped at ``width``."""
    font = int(rng.choice(_FONTS))
    scale = line_h / 30.0
    thick = max(1, int(round(line_h / 18)))
    for li in range(lines):
        cx = x
        by = int(y + li * line_h * 1.35)
        if by > img.shape[0] + line_h:
            break
        while True:
            word = pseudo_word(rng)
            (tw, _), _ = cv2.getTextSize(word, font, scale, thick)
            if cx + tw > x + width:
                break
            cv2.putText(img, word, (int(cx), by), font, scale, col, thick, cv2.LINE_AA)
            cx += tw + line_h * 0.45


def _draw_text(img: np.ndarray, rng: np.random.Generator, blocks: int, height_range: tuple[float, float]) -> None:
    h, w = img.shape
    for _ in range(blocks):
        lh = float(np.exp(rng.uniform(np.log(height_range[0]), np.log(height_range[1]))))
        bw = int(rng.uniform(0.2, 0.6) * w)
        x = int(rng.integers(-bw // 4, max(1, w - bw // 2)))
        y = int(rng.integers(int(lh), max(int(lh) + 1, h)))
        col = _grey(rng, 0, 60) if rng.random() < 0.7 else _grey(rng, 200, 255)
        _draw_text_block(img, rng, x, y, bw, lh, int(rng.integers(1, 6)), col)


def _to_u8(f: np.ndarray, mean: float, std: float) -> np.ndarray:
    return np.clip(f * std + mean, 0, 255).astype(np.uint8)


def _style_wall(rng, h, w, px):
    img = _to_u8(value_noise(rng, (h, w), beta=0.9), 150, 38)
    _draw_shapes(img, rng, int(h * w / 2500), (px * 3, px * 60))
    # posters / notes: light rectangles with text and shapes inside
    for _ in range(max(2, int(h * w / 60000))):
        pw, ph = int(rng.uniform(0.08, 0.25) * w), int(rng.uniform(0.08, 0.3) * h)
        x0, y0 = int(rng.integers(0, max(1, w - pw))), int(rng.integers(0, max(1, h - ph)))
        sub = img[y0:y0 + ph, x0:x0 + pw]
        sub[:] = _to_u8(value_noise(rng, sub.shape, coarsest=32, beta=0.5), _grey(rng, 120, 230), 18)
        _draw_shapes(sub, rng, int(sub.size / 800) + 3, (px * 2, px * 20))
        _draw_text(sub, rng, 2, (px * 2.0, px * 6.0))
    _draw_text(img, rng, int(h * w / 40000) + 2, (px * 3, px * 12))
    return img


def _style_floor(rng, h, w, px):
    img = _to_u8(value_noise(rng, (h, w), beta=0.6), 120, 45)
    _draw_shapes(img, rng, int(h * w / 1200), (px * 2, px * 30))
    _draw_text(img, rng, int(h * w / 80000) + 2, (px * 4, px * 12))
    return img


def _style_wood(rng, h, w, px):
    grain = value_noise(rng, (h, w), coarsest=64, finest=2, beta=0.8, stretch=(6.0, 0.7))
    blotch = value_noise(rng, (h, w), beta=0.6)
    img = _to_u8(0.8 * grain + 0.6 * blotch, 135, 32)
    for _ in range(max(2, int(h * w / 150000))):  # knots
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        for r in range(int(rng.integers(4, 10)), 0, -1):
            cv2.ellipse(img, (cx, cy), (int(r * px * 3 * rng.uniform(1.5, 3.0)), int(r * px * 1.5)), 0, 0, 360,
                        _grey(rng, 40, 200), max(1, int(px)), cv2.LINE_AA)
    # printed sheets and marks lying on the table
    _draw_shapes(img, rng, int(h * w / 3000), (px * 2, px * 25))
    for _ in range(max(1, int(h * w / 250000))):
        pw, ph = int(rng.uniform(0.1, 0.2) * w), int(rng.uniform(0.1, 0.25) * h)
        x0, y0 = int(rng.integers(0, max(1, w - pw))), int(rng.integers(0, max(1, h - ph)))
        sub = img[y0:y0 + ph, x0:x0 + pw]
        sub[:] = _to_u8(value_noise(rng, sub.shape, coarsest=16, beta=0.3), 225, 6)
        _draw_text(sub, rng, 4, (px * 3, px * 8))
        _draw_shapes(sub, rng, 6, (px * 4, px * 20))
    return img


def _style_box(rng, h, w, px):
    img = _to_u8(value_noise(rng, (h, w), beta=0.7), _grey(rng, 90, 180), 30)
    _draw_shapes(img, rng, int(h * w / 2500) + 4, (px * 3, px * 40))
    for _ in range(int(rng.integers(1, 3))):  # labels
        pw, ph = int(rng.uniform(0.3, 0.6) * w), int(rng.uniform(0.15, 0.35) * h)
        x0, y0 = int(rng.integers(0, max(1, w - pw))), int(rng.integers(0, max(1, h - ph)))
        cv2.rectangle(img, (x0, y0), (x0 + pw, y0 + ph), _grey(rng, 200, 250), -1)
        cv2.rectangle(img, (x0, y0), (x0 + pw, y0 + ph), _grey(rng, 0, 50), max(1, int(px)))
        _draw_text_block(img, rng, x0 + int(3 * px), y0 + int(ph * 0.3), pw - int(6 * px), max(6.0, ph / 5), 4,
                         _grey(rng, 0, 60))
    _draw_text(img, rng, 3, (px * 4, px * 14))
    return img


def _style_book(rng, h, w, px):
    base = _grey(rng, 40, 220)
    img = _to_u8(value_noise(rng, (h, w), coarsest=64, beta=0.5), base, 12)
    dark = base > 128
    ink = _grey(rng, 0, 50) if dark else _grey(rng, 205, 255)
    m = int(min(h, w) * 0.06)
    cv2.rectangle(img, (m, m), (w - m, h - m), ink, max(1, int(min(h, w) / 80)), cv2.LINE_AA)
    title_h = max(8.0, min(h, w) * 0.09)
    _draw_text_block(img, rng, 2 * m, int(2 * m + title_h), w - 4 * m, title_h, 2, ink)
    _draw_shapes(img, rng, 10 + int(h * w / 8000), (min(h, w) * 0.02, min(h, w) * 0.25))
    _draw_text_block(img, rng, 2 * m, int(h * 0.55), w - 4 * m, max(5.0, title_h / 3.0), 8, ink)
    return img


_STYLE_FUNCS = {"wall": _style_wall, "floor": _style_floor, "wood": _style_wood, "box": _style_box, "book": _style_book}


def make_texture(seed: int, size_hw: tuple[int, int], style: str = "wall", key: int = 0,
                 shading: float = 1.0, texel_px: float = 1.0) -> np.ndarray:
    """An ``(h, w)`` uint8 texture; a pure function of its arguments.

    ``key`` distinguishes textures drawn from one scene seed, ``shading`` (0-1.3) scales the
    brightness (baked-in lighting of a face), ``texel_px`` is the number of texels one image
    pixel covers at the typical viewing distance: shapes and print are sized in multiples of
    it (a few pixels up to about a hundred) so that they suit the camera, not the texel grid.
    """
    if style not in _STYLE_FUNCS:
        raise ValueError(f"unknown texture style {style!r}; known: {', '.join(STYLES)}")
    h, w = int(size_hw[0]), int(size_hw[1])
    if h < 1 or w < 1:
        raise ValueError(f"texture size must be positive, got {h}x{w}")
    rng = _rng(seed, key, 7919)
    img = _STYLE_FUNCS[style](rng, h, w, max(0.5, float(texel_px)))
    # texel-level grain, then band-limit the drawn edges
    grain = rng.standard_normal((h, w)).astype(np.float32) * 5.0
    f = img.astype(np.float32) + grain
    f = cv2.GaussianBlur(f, (0, 0), 0.5)
    if shading != 1.0:
        f = (f - 128.0) * shading + 128.0 * shading
    return np.clip(f + 0.5, 0, 255).astype(np.uint8)
