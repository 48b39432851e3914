"""The built-in demo route: a small drawn street, so the app and CLI run with no download.

A procedurally generated side-looking drive along one street, seen in three conditions
(``day``, ``night``, ``snow``). Frame ``f`` is the same spot in every condition: the
camera moves ``_STEP`` facade pixels per frame, so neighbouring frames overlap by about
90 % and frames ten apart share nothing. Layers move with parallax (far hills slowly,
the road fast), each condition's camera is offset a few pixels and every frame is
jittered a little in shift and zoom, so no two images are pixel-identical.

What it is: a teaching route whose difficulty sits between trivial and hopeless for a
plain image similarity (night -> day nearest neighbour is right for most, not all,
frames), so thresholds, places and failures can be shown on a fresh machine.
What it is not: a benchmark. Its statistics say nothing about real places; use
GardensPoint or Nordland for numbers.

Frames are PNG, not JPEG: the pixels are exactly what the generator drew, whatever
codec is installed, and a given Pillow/zlib build writes the same bytes every time (no
timestamps or EXIF). Bytes may still differ between zlib builds (zlib vs zlib-ng), which
only costs the content-hashed descriptor cache a miss; JPEG could differ in pixels too.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from vpr_explorer.data.traversals import Dataset, load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import CACHE_ENV, cache_root

DEMO_TRAVERSALS = ("day", "night", "snow")
DEMO_FRAMES = 60
DEMO_SEED = 0
DEMO_VERSION = 1
"""Bump whenever the drawing changes: it is part of the cache folder name."""
DEMO_MAX_FRAMES = 500
FRAME_SIZE = (320, 240)
"""``(width, height)`` of every frame."""

MARKER = "route.json"
README = "README.txt"
POSITIONS = "positions.csv"
_FRAME_NAME = re.compile(r"^frame_\d{3}\.png$")

# Panorama geometry, in facade pixels (the frame's scale at zoom 1).
_PANO_H = 264
_GROUND_Y = 186  # foot of the facades, top of the sidewalk
_KERB_Y = 202  # sidewalk meets road
_STEP = 32  # camera advance per frame
_X0 = 200  # left margin of every layer, so jittered views never leave it
_MAX_SHIFT = 14  # |condition offset| + |jitter|, bounds the layer widths

# Parallax of each layer (layer pixels per camera pixel), drawn back to front.
_PARALLAX = {"sky": 0.06, "far": 0.35, "facade": 1.0, "street": 1.15, "road": 1.45, "cars": 1.3}

# Each condition's camera path: (x offset, y offset) in pixels, like a second drive
# that keeps a slightly different line.
_COND_OFFSET = {"day": (0, 0), "night": (3, 1), "snow": (-4, -1)}

_WALLS = (
    (222, 206, 170), (196, 120, 92), (170, 178, 188), (230, 222, 205), (150, 92, 72),
    (205, 180, 110), (140, 160, 150), (235, 200, 180), (120, 128, 150), (214, 150, 90),
    (180, 196, 170), (245, 236, 220),
)
_ROOFS = ((150, 70, 55), (80, 86, 98), (110, 80, 60), (70, 110, 100), (60, 60, 66))
_BRIGHT = ((205, 40, 45), (30, 120, 200), (30, 150, 80), (240, 170, 30), (150, 60, 170), (240, 120, 40))
_GREENS = ((70, 120, 55), (55, 105, 60), (90, 135, 60), (45, 90, 50), (100, 140, 75))


@dataclass(frozen=True)
class _Shape:
    """One filled primitive of a layer; its colour is chosen per condition from ``role``."""

    kind: str  # "rect" | "poly" | "ellipse" | "line"
    xy: tuple[int, ...]
    role: str
    rgb: tuple[int, int, int]
    u: float = 1.0  # per-shape uniform draw; windows and signs are lit at night when u < 0.5
    conds: frozenset[str] | None = None  # conditions that show the shape (None: all)
    width: int = 1  # line width


@dataclass(frozen=True)
class _Layer:
    name: str
    width: int
    shapes: tuple[_Shape, ...]


@dataclass(frozen=True)
class _Scene:
    """Everything random about the route, drawn once and rendered in every condition."""

    layers: tuple[_Layer, ...]
    lamps: tuple[tuple[int, int], ...]  # lamp heads (x, y) in street-layer pixels


# --------------------------------------------------------------------------- validation


def _check_params(seed: object, n_frames: object) -> tuple[int, int]:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise VPRInputError(f"seed must be a non-negative integer, got {seed!r}")
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)):
        raise VPRInputError(f"n_frames must be an integer, got {n_frames!r}")
    if not 10 <= n_frames <= DEMO_MAX_FRAMES:
        raise VPRInputError(f"n_frames must be between 10 and {DEMO_MAX_FRAMES}, got {n_frames}")
    return int(seed), int(n_frames)


# --------------------------------------------------------------------------- the scene


def _vary(rgb: tuple[int, ...], rng: np.random.Generator, amount: int) -> tuple[int, int, int]:
    d = rng.integers(-amount, amount + 1, size=3)
    return tuple(int(np.clip(c + e, 0, 255)) for c, e in zip(rgb, d))  # type: ignore[return-value]


def _pick(rng: np.random.Generator, palette: tuple) -> tuple[int, int, int]:
    return palette[int(rng.integers(len(palette)))]


class _Canvas:
    """Collects shapes with integer coordinates."""

    def __init__(self) -> None:
        self.shapes: list[_Shape] = []

    def add(self, kind: str, xy, role: str, rgb, *, u: float = 1.0, conds=None, width: int = 1) -> None:
        coords = tuple(int(round(float(v))) for v in xy)
        self.shapes.append(_Shape(kind, coords, role, tuple(int(c) for c in rgb), float(u), conds, width))

    def rect(self, x0, y0, x1, y1, role, rgb, **kw) -> None:
        self.add("rect", (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)), role, rgb, **kw)


_SNOW = frozenset({"snow"})
_NIGHT = frozenset({"night"})


def _window(c: _Canvas, rng: np.random.Generator, x0, y0, x1, y1, lit_p: float, glass=None) -> None:
    lit = rng.random() < lit_p
    u = rng.random() * 0.5 if lit else 0.5 + rng.random() * 0.5
    glass = glass or _vary((62, 78, 98), rng, 14)
    c.rect(x0 - 1, y0 - 1, x1 + 1, y1 + 1, "trim", (235, 232, 222))
    c.rect(x0, y0, x1, y1, "window", glass, u=u)
    if rng.random() < 0.35:  # a drawn blind: lighter upper part by day
        c.rect(x0, y0, x1, y0 + (y1 - y0) // 3, "blind", (200, 195, 180), u=u)
    c.rect(x0 - 1, y1 + 1, x1 + 1, y1 + 2, "snowcap", (240, 242, 246), conds=_SNOW)


def _building(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    w = int(rng.integers(50, 126))
    floors = int(rng.integers(2, 7))
    fh = int(rng.integers(19, 25))
    h = floors * fh + int(rng.integers(4, 12))
    top = _GROUND_Y - h
    wall = _vary(_pick(rng, _WALLS), rng, 14)
    c.rect(x, top, x + w, _GROUND_Y, "wall", wall)
    c.rect(x + w - 6, top, x + w, _GROUND_Y, "shade", wall)
    roof = _vary(_pick(rng, _ROOFS), rng, 10)
    kind = int(rng.integers(4))
    if kind == 0:  # flat with cornice
        c.rect(x - 2, top - 4, x + w + 2, top, "trim", tuple(int(v * 0.75) for v in wall))
        c.rect(x - 2, top - 8, x + w + 2, top - 5, "snowcap", (240, 242, 246), conds=_SNOW)
    elif kind == 1:  # gable
        rh = int(rng.integers(14, 34))
        c.add("poly", (x - 3, top, x + w + 3, top, x + w // 2, top - rh), "roof", roof)
    elif kind == 2:  # mansard
        rh = int(rng.integers(12, 20))
        c.add("poly", (x - 2, top, x + w + 2, top, x + w - 8, top - rh, x + 8, top - rh), "roof", roof)
        for dx in range(x + 14, x + w - 14, 22):
            c.rect(dx, top - rh + 4, dx + 8, top - 3, "window", (62, 78, 98), u=0.5 + 0.5 * rng.random())
    else:  # stepped parapet
        c.rect(x + 6, top - 6, x + w - 6, top, "wall", wall)
        c.rect(x + w // 3, top - 12, x + 2 * w // 3, top - 6, "wall", wall)
        c.rect(x + 6, top - 9, x + w - 6, top - 6, "snowcap", (240, 242, 246), conds=_SNOW)
    ww = int(rng.integers(7, 14))
    wh = int(rng.integers(9, fh - 5))
    gap = int(rng.integers(6, 13))
    ncol = max(1, (w - 8) // (ww + gap))
    x_start = x + (w - (ncol * ww + (ncol - 1) * gap)) // 2
    lit_p = float(rng.uniform(0.02, 0.2))
    for k in range(1, floors):
        y1 = _GROUND_Y - k * fh - 4
        for j in range(ncol):
            wx = x_start + j * (ww + gap)
            _window(c, rng, wx, y1 - wh, wx + ww, y1, lit_p)
    if rng.random() < 0.5:  # shop: big window, awning, sign
        sx0, sx1 = x + 6, x + w - 6
        _window(c, rng, sx0, _GROUND_Y - fh + 8, sx1 - 18 if w > 60 else sx1, _GROUND_Y - 2, lit_p + 0.3)
        if w > 60:
            c.rect(sx1 - 14, _GROUND_Y - fh + 6, sx1, _GROUND_Y, "door", _vary((90, 60, 40), rng, 20))
        colour = _pick(rng, _BRIGHT)
        c.add("poly", (sx0 - 2, _GROUND_Y - fh + 2, sx1 + 2, _GROUND_Y - fh + 2, sx1 + 5, _GROUND_Y - fh + 9,
                       sx0 - 5, _GROUND_Y - fh + 9), "awning", colour)
        for sx in range(sx0, sx1, 10):
            c.rect(sx, _GROUND_Y - fh + 2, sx + 4, _GROUND_Y - fh + 8, "awning", (240, 238, 230))
        c.rect(sx0 - 5, _GROUND_Y - fh, sx1 + 5, _GROUND_Y - fh + 1, "snowcap", (240, 242, 246), conds=_SNOW)
    else:
        dx = x + int(rng.integers(6, max(7, w - 20)))
        c.rect(dx, _GROUND_Y - 17, dx + 11, _GROUND_Y, "door", _vary(_pick(rng, _BRIGHT + ((90, 60, 40),)), rng, 20))
    return w


def _church(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    stone = _vary((178, 168, 148), rng, 8)
    slate = (78, 84, 96)
    c.rect(x, _GROUND_Y - 80, x + 112, _GROUND_Y, "wall", stone)
    c.add("poly", (x - 4, _GROUND_Y - 80, x + 116, _GROUND_Y - 80, x + 56, _GROUND_Y - 122), "roof", slate)
    c.add("ellipse", (x + 44, _GROUND_Y - 104, x + 68, _GROUND_Y - 84), "window", (150, 60, 130), u=0.2)
    for wx in range(x + 10, x + 100, 22):
        c.add("ellipse", (wx, _GROUND_Y - 66, wx + 10, _GROUND_Y - 56), "window", (90, 70, 120), u=0.3)
        c.rect(wx, _GROUND_Y - 61, wx + 10, _GROUND_Y - 30, "window", (90, 70, 120), u=0.3)
    tx = x + 112
    c.rect(tx, _GROUND_Y - 150, tx + 32, _GROUND_Y, "wall", stone)
    c.rect(tx + 27, _GROUND_Y - 150, tx + 32, _GROUND_Y, "shade", stone)
    c.add("poly", (tx - 3, _GROUND_Y - 150, tx + 35, _GROUND_Y - 150, tx + 16, _GROUND_Y - 182), "roof", slate)
    c.add("ellipse", (tx + 6, _GROUND_Y - 138, tx + 26, _GROUND_Y - 118), "clock", (240, 238, 225), u=0.1)
    c.add("line", (tx + 16, _GROUND_Y - 128, tx + 16, _GROUND_Y - 136), "metal", (30, 30, 30), width=2)
    c.add("line", (tx + 16, _GROUND_Y - 128, tx + 22, _GROUND_Y - 128), "metal", (30, 30, 30), width=2)
    c.add("ellipse", (tx + 7, _GROUND_Y - 40, tx + 25, _GROUND_Y - 22), "door", (80, 50, 35))
    c.rect(tx + 7, _GROUND_Y - 31, tx + 25, _GROUND_Y, "door", (80, 50, 35))
    return 144


def _town_hall(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    wall = _vary((212, 176, 118), rng, 8)
    c.rect(x, _GROUND_Y - 96, x + 136, _GROUND_Y, "wall", wall)
    c.rect(x - 3, _GROUND_Y - 101, x + 139, _GROUND_Y - 96, "trim", (240, 236, 220))
    c.rect(x - 3, _GROUND_Y - 105, x + 139, _GROUND_Y - 102, "snowcap", (240, 242, 246), conds=_SNOW)
    for k in range(3):
        y1 = _GROUND_Y - 10 - k * 30
        for wx in range(x + 8, x + 128, 16):
            if x + 52 <= wx <= x + 76:
                continue
            _window(c, rng, wx, y1 - 18, wx + 8, y1, 0.45)
    tx = x + 50
    c.rect(tx, _GROUND_Y - 150, tx + 36, _GROUND_Y, "wall", wall)
    c.add("poly", (tx - 4, _GROUND_Y - 150, tx + 40, _GROUND_Y - 150, tx + 18, _GROUND_Y - 176), "copper", (90, 156, 132))
    c.add("ellipse", (tx + 5, _GROUND_Y - 144, tx + 31, _GROUND_Y - 118), "clock", (244, 242, 230), u=0.1)
    c.add("line", (tx + 18, _GROUND_Y - 131, tx + 18, _GROUND_Y - 141), "metal", (30, 30, 30), width=2)
    c.add("line", (tx + 18, _GROUND_Y - 131, tx + 25, _GROUND_Y - 127), "metal", (30, 30, 30), width=2)
    c.add("line", (tx + 18, _GROUND_Y - 176, tx + 18, _GROUND_Y - 196), "metal", (60, 60, 60), width=2)
    c.add("poly", (tx + 19, _GROUND_Y - 196, tx + 34, _GROUND_Y - 191, tx + 19, _GROUND_Y - 186), "flag", (200, 40, 40))
    c.rect(tx + 8, _GROUND_Y - 30, tx + 28, _GROUND_Y, "door", (70, 45, 30))
    return 136


def _glass_tower(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    w, h = 104, 176
    c.rect(x, _GROUND_Y - h, x + w, _GROUND_Y, "metal", (70, 80, 92))
    lit_p = float(rng.uniform(0.25, 0.6))
    for y in range(_GROUND_Y - h + 6, _GROUND_Y - 22, 12):
        for gx in range(x + 4, x + w - 4, 12):
            shade = (90 + (gx - x) // 3, 140 + (y - _GROUND_Y) // 6, 190)
            lit = rng.random() < lit_p
            u = rng.random() * 0.5 if lit else 0.5 + rng.random() * 0.5
            c.rect(gx, y, gx + 9, y + 9, "glass", shade, u=u)
    c.rect(x - 2, _GROUND_Y - h - 6, x + w + 2, _GROUND_Y - h, "metal", (50, 55, 62))
    c.rect(x + 10, _GROUND_Y - 20, x + w - 10, _GROUND_Y, "window", (50, 60, 75), u=0.1)
    c.rect(x + 20, _GROUND_Y - 30, x + w - 20, _GROUND_Y - 24, "sign", (30, 120, 200), u=0.1)
    return w


def _mural(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    w, h = 112, 104
    c.rect(x, _GROUND_Y - h, x + w, _GROUND_Y, "wall", (236, 232, 222))
    c.rect(x - 2, _GROUND_Y - h - 4, x + w + 2, _GROUND_Y - h, "trim", (120, 120, 120))
    c.rect(x - 2, _GROUND_Y - h - 8, x + w + 2, _GROUND_Y - h - 5, "snowcap", (240, 242, 246), conds=_SNOW)
    for i, col in enumerate(rng.permutation(len(_BRIGHT))[:4]):
        c.rect(x + 6, _GROUND_Y - h + 8 + 18 * i, x + w - 6, _GROUND_Y - h + 20 + 18 * i, "paint", _BRIGHT[col])
    cx, cy = x + w // 2 + int(rng.integers(-20, 21)), _GROUND_Y - h // 2
    c.add("ellipse", (cx - 30, cy - 30, cx + 30, cy + 30), "paint", (250, 210, 40))
    c.add("ellipse", (cx - 16, cy - 16, cx + 16, cy + 16), "paint", (30, 30, 40))
    return w


def _factory(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    brick = _vary((152, 72, 52), rng, 8)
    w = 150
    c.rect(x, _GROUND_Y - 70, x + w, _GROUND_Y, "wall", brick)
    for k in range(3):
        tx = x + k * 50
        c.add("poly", (tx, _GROUND_Y - 70, tx + 50, _GROUND_Y - 70, tx + 50, _GROUND_Y - 96), "roof", (90, 94, 100))
        c.rect(tx + 42, _GROUND_Y - 92, tx + 49, _GROUND_Y - 72, "window", (160, 180, 190), u=0.7)
    for wx in range(x + 10, x + w - 10, 24):
        c.add("ellipse", (wx, _GROUND_Y - 58, wx + 16, _GROUND_Y - 44), "window", (62, 78, 98), u=0.6)
        c.rect(wx, _GROUND_Y - 51, wx + 16, _GROUND_Y - 20, "window", (62, 78, 98), u=0.6 if wx % 3 else 0.3)
    cx = x + 20
    c.rect(cx, _GROUND_Y - 200, cx + 14, _GROUND_Y - 70, "wall", brick)
    c.rect(cx - 1, _GROUND_Y - 192, cx + 15, _GROUND_Y - 186, "paint", (235, 235, 235))
    c.rect(cx - 1, _GROUND_Y - 180, cx + 15, _GROUND_Y - 174, "paint", (200, 40, 40))
    c.add("ellipse", (cx + 3, _GROUND_Y - 203, cx + 11, _GROUND_Y - 199), "beacon", (200, 50, 40), u=0.0)
    return w


def _billboard(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    w = 120
    c.rect(x, _GROUND_Y - 16, x + w, _GROUND_Y, "trim", (150, 146, 140))
    for hx in range(x + 4, x + w - 4, 14):
        c.add("ellipse", (hx, _GROUND_Y - 28, hx + 18, _GROUND_Y - 12), "foliage", _vary(_pick(rng, _GREENS), rng, 10))
    c.rect(x + 30, _GROUND_Y - 100, x + 34, _GROUND_Y - 16, "metal", (90, 90, 95))
    c.rect(x + 86, _GROUND_Y - 100, x + 90, _GROUND_Y - 16, "metal", (90, 90, 95))
    bx0, by0 = x + 6, _GROUND_Y - 156
    c.rect(bx0, by0, bx0 + 108, by0 + 60, "billboard", _pick(rng, _BRIGHT), u=0.2)
    c.rect(bx0 + 8, by0 + 10, bx0 + 60, by0 + 28, "billboard", (250, 250, 245), u=0.2)
    c.add("ellipse", (bx0 + 66, by0 + 8, bx0 + 102, by0 + 52), "billboard", _pick(rng, _BRIGHT), u=0.2)
    c.rect(bx0 - 2, by0 - 3, bx0 + 110, by0, "snowcap", (240, 242, 246), conds=_SNOW)
    return w


_LANDMARKS = (_church, _town_hall, _glass_tower, _mural, _factory, _billboard)


def _gap(c: _Canvas, rng: np.random.Generator, x: int) -> int:
    w = int(rng.integers(18, 50))
    c.rect(x, _GROUND_Y - 12, x + w, _GROUND_Y, "trim", _vary((160, 150, 140), rng, 12))
    c.rect(x, _GROUND_Y - 15, x + w, _GROUND_Y - 12, "snowcap", (240, 242, 246), conds=_SNOW)
    return w


def _facade(rng: np.random.Generator, width: int) -> tuple[_Shape, ...]:
    c = _Canvas()
    c.rect(0, _GROUND_Y, width, _KERB_Y, "pavement", (178, 174, 166))
    for x in range(0, width, 26):
        c.add("line", (x, _GROUND_Y, x - 6, _KERB_Y), "joint", (140, 136, 130))
    order = list(rng.permutation(len(_LANDMARKS)))
    x = int(rng.integers(0, 20))
    next_landmark = x + float(rng.uniform(120, 260))
    while x < width:
        if x >= next_landmark:
            if not order:
                order = list(rng.permutation(len(_LANDMARKS)))
            w = _LANDMARKS[order.pop()](c, rng, x)
            next_landmark = x + w + float(rng.uniform(200, 380))
        elif rng.random() < 0.1:
            w = _gap(c, rng, x)
        else:
            w = _building(c, rng, x)
        x += w + int(rng.integers(0, 4))
    return tuple(c.shapes)


def _street(rng: np.random.Generator, width: int) -> tuple[tuple[_Shape, ...], tuple[tuple[int, int], ...]]:
    c = _Canvas()
    lamps = []
    base = _KERB_Y - 1
    x = float(rng.uniform(10, 60))
    while x < width:
        kind = rng.choice(4, p=(0.42, 0.36, 0.12, 0.10))
        xi = int(x)
        if kind == 0:  # deciduous or conifer tree
            th = int(rng.integers(30, 60))
            c.rect(xi - 3, base - th, xi + 3, base, "trunk", (92, 66, 44))
            if rng.random() < 0.75:
                r = int(rng.integers(16, 28))
                for _ in range(5):
                    dx, dy = rng.integers(-r // 2, r // 2 + 1, size=2)
                    rr = int(r * rng.uniform(0.6, 1.0))
                    cx, cy = xi + int(dx), base - th - r // 2 + int(dy)
                    c.add("ellipse", (cx - rr, cy - rr, cx + rr, cy + rr), "foliage", _vary(_pick(rng, _GREENS), rng, 12))
            else:
                r = int(rng.integers(14, 22))
                for k in range(3):
                    y0 = base - th + 10 - k * 18
                    c.add("poly", (xi - r + 3 * k, y0, xi + r - 3 * k, y0, xi, y0 - 30), "foliage", (40, 85, 55))
        elif kind == 1:  # street lamp
            top = base - int(rng.integers(110, 130))
            c.rect(xi - 2, top, xi + 2, base, "metal", (70, 74, 80))
            c.rect(xi - 2, top, xi + 16, top + 3, "metal", (70, 74, 80))
            c.add("ellipse", (xi + 10, top + 1, xi + 24, top + 8), "lamp", (210, 210, 200))
            lamps.append((xi + 17, top + 6))
        elif kind == 2:  # traffic sign
            top = base - int(rng.integers(50, 70))
            c.rect(xi - 1, top, xi + 1, base, "metal", (120, 124, 130))
            colour = ((210, 40, 40), (40, 90, 190))[int(rng.integers(2))]
            c.add("ellipse", (xi - 9, top - 9, xi + 9, top + 9), "sign", colour, u=0.7)
            c.add("ellipse", (xi - 6, top - 6, xi + 6, top + 6), "sign", (245, 245, 245), u=0.7)
        else:  # bus shelter
            c.rect(xi, base - 40, xi + 44, base - 36, "metal", (90, 94, 100))
            c.rect(xi + 2, base - 36, xi + 42, base - 4, "window", (150, 180, 190), u=0.6)
            c.rect(xi + 30, base - 34, xi + 40, base - 14, "billboard", _pick(rng, _BRIGHT), u=0.2)
            c.rect(xi, base - 43, xi + 44, base - 40, "snowcap", (240, 242, 246), conds=_SNOW)
            x += 40
        x += float(rng.uniform(40, 110))
    return tuple(c.shapes), tuple(lamps)


def _road(rng: np.random.Generator, width: int) -> tuple[_Shape, ...]:
    c = _Canvas()
    c.rect(0, _KERB_Y, width, _PANO_H, "road", (74, 74, 80))
    c.rect(0, _KERB_Y, width, _KERB_Y + 4, "kerb", (160, 158, 152))
    c.rect(0, _KERB_Y + 12, width, _KERB_Y + 13, "marking", (230, 230, 220))
    phase = int(rng.integers(0, 60))
    for x in range(-phase, width, 60):
        c.rect(x, _KERB_Y + 40, x + 30, _KERB_Y + 43, "marking", (236, 236, 226))
    x = float(rng.uniform(100, 300))
    while x < width:
        xi = int(x)
        if rng.random() < 0.5:  # pedestrian crossing, seen from the side
            for k in range(5):
                c.rect(xi, _KERB_Y + 8 + 10 * k, xi + 46, _KERB_Y + 12 + 10 * k, "marking", (240, 240, 232))
        else:
            c.add("ellipse", (xi, _KERB_Y + 24, xi + 22, _KERB_Y + 29), "metal", (50, 50, 54))
        x += float(rng.uniform(250, 500))
    for k, y in enumerate((_KERB_Y + 20, _KERB_Y + 30, _KERB_Y + 50)):
        c.rect(0, y, width, y + 3 + k, "track", (150, 152, 158), conds=_SNOW)
    return tuple(c.shapes)


def _cars(rng: np.random.Generator, width: int) -> tuple[_Shape, ...]:
    c = _Canvas()
    x = float(rng.uniform(40, 200))
    while x < width:
        xi = int(x)
        present = frozenset(t for t in DEMO_TRAVERSALS if rng.random() < 0.55)
        body = _vary(_pick(rng, _BRIGHT + ((200, 200, 205), (30, 30, 35), (240, 240, 240))), rng, 15)
        bl = int(rng.integers(58, 74))
        yb = _KERB_Y + 26
        if present:
            c.add("poly", (xi + 12, yb - 16, xi + 18, yb - 28, xi + bl - 22, yb - 28, xi + bl - 12, yb - 16),
                  "car", body, conds=present)
            c.add("poly", (xi + 17, yb - 17, xi + 21, yb - 26, xi + bl - 24, yb - 26, xi + bl - 16, yb - 17),
                  "carglass", (60, 70, 85), conds=present)
            c.rect(xi, yb - 17, xi + bl, yb - 4, "car", body, conds=present)
            c.rect(xi + bl - 4, yb - 15, xi + bl, yb - 11, "headlight", (240, 230, 180), conds=present)
            for wx in (xi + 8, xi + bl - 22):
                c.add("ellipse", (wx, yb - 11, wx + 14, yb + 3), "tyre", (25, 25, 28), conds=present)
            if "snow" in present:
                c.rect(xi + 18, yb - 31, xi + bl - 22, yb - 28, "snowcap", (240, 242, 246), conds=_SNOW)
        x += float(rng.uniform(110, 320)) + bl
    return tuple(c.shapes)


def _sky(rng: np.random.Generator, width: int) -> tuple[_Shape, ...]:
    c = _Canvas()
    for _ in range(max(3, width // 70)):
        cx, cy = float(rng.uniform(0, width)), float(rng.uniform(14, 90))
        for _ in range(4):
            dx, dy, rx, ry = rng.uniform(-26, 26), rng.uniform(-6, 6), rng.uniform(14, 30), rng.uniform(7, 13)
            c.add("ellipse", (cx + dx - rx, cy + dy - ry, cx + dx + rx, cy + dy + ry), "cloud", (250, 250, 252),
                  conds=frozenset({"day", "snow"}))
    for _ in range(width // 6):
        sx, sy = float(rng.uniform(0, width)), float(rng.uniform(0, 120))
        c.rect(sx, sy, sx + 1, sy + 1, "star", (200, 205, 220), conds=_NIGHT)
    mx = float(rng.uniform(_X0 - 40, _X0 + 40))
    c.add("ellipse", (mx, 20, mx + 18, 38), "moon", (235, 232, 210), conds=_NIGHT)
    c.add("ellipse", (mx - 40, 10, mx - 10, 40), "sun", (255, 248, 215), conds=frozenset({"day"}))
    return tuple(c.shapes)


def _far(rng: np.random.Generator, width: int) -> tuple[_Shape, ...]:
    c = _Canvas()
    xs = np.arange(0, width + 40, 40)
    walk = np.cumsum(rng.normal(0, 9, size=len(xs)))
    ys = _GROUND_Y - 55 - 20 * np.sin(xs / 230.0 + rng.uniform(0, 6)) - (walk - walk.mean()) * 0.4
    ys = np.clip(ys, 70, _GROUND_Y - 20)
    pts: list[float] = [0, _GROUND_Y]
    for x, y in zip(xs, ys):
        pts += [float(x), float(y)]
    pts += [float(xs[-1]), _GROUND_Y]
    c.add("poly", pts, "hill", (132, 158, 146))
    x = float(rng.uniform(60, 200))
    while x < width:
        xi, base = int(x), int(np.interp(x, xs, ys)) + 10
        kind = int(rng.integers(3))
        if kind == 0:  # radio mast with a beacon
            c.add("poly", (xi - 6, base, xi + 6, base, xi, base - 90), "farbuilding", (150, 156, 170))
            c.add("ellipse", (xi - 2, base - 93, xi + 2, base - 89), "beacon", (200, 50, 40), u=0.0)
        elif kind == 1:  # domed building
            c.rect(xi, base - 30, xi + 50, base, "farbuilding", (160, 166, 178))
            c.add("ellipse", (xi + 10, base - 52, xi + 40, base - 22), "farbuilding", (160, 166, 178))
        else:  # two towers
            c.rect(xi, base - 70, xi + 14, base, "farbuilding", (146, 152, 166))
            c.rect(xi + 20, base - 56, xi + 34, base, "farbuilding", (146, 152, 166))
        x += float(rng.uniform(180, 420))
    return tuple(c.shapes)


def _layer_width(parallax: float, n_frames: int) -> int:
    return int(np.ceil(2 * _X0 + parallax * ((n_frames - 1) * _STEP + _MAX_SHIFT)))


def _scene(seed: int, n_frames: int) -> _Scene:
    """Draw everything random about the route; each layer has its own stream so that
    e.g. the trees do not move when a building is added."""
    w = {name: _layer_width(p, n_frames) for name, p in _PARALLAX.items()}
    streams = {name: np.random.default_rng([seed, k]) for k, name in enumerate(_PARALLAX)}
    street, lamps = _street(streams["street"], w["street"])
    shapes = {
        "sky": _sky(streams["sky"], w["sky"]),
        "far": _far(streams["far"], w["far"]),
        "facade": _facade(streams["facade"], w["facade"]),
        "street": street,
        "road": _road(streams["road"], w["road"]),
        "cars": _cars(streams["cars"], w["cars"]),
    }
    return _Scene(tuple(_Layer(name, w[name], shapes[name]) for name in _PARALLAX), lamps)


# --------------------------------------------------------------------------- conditions


def _grey(rgb) -> float:
    return 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]


def _mix(a, b, t: float) -> tuple[int, int, int]:
    return tuple(int(round(x * (1 - t) + y * t)) for x, y in zip(a, b))  # type: ignore[return-value]


def _night_dark(rgb) -> tuple[int, int, int]:
    return tuple(int(round(c * 0.24 + d)) for c, d in zip(rgb, (4, 6, 18)))  # type: ignore[return-value]


def _snow_desat(rgb) -> tuple[int, int, int]:
    g = _grey(rgb)
    return _mix(_mix(rgb, (g, g, g), 0.6), (222, 224, 228), 0.2)


_SNOW_WHITE = {
    "roof": (236, 238, 242), "copper": (236, 238, 242), "snowcap": (242, 244, 248), "pavement": (228, 230, 234),
    "joint": (214, 216, 220), "road": (214, 216, 220), "kerb": (236, 238, 242), "marking": (204, 206, 210),
    "hill": (230, 232, 236),
}
_NIGHT_FIXED = {
    "lamp": (255, 244, 200), "marking": (92, 92, 86), "road": (28, 28, 34), "kerb": (58, 58, 62), "moon": (235, 232, 210),
    "star": (190, 196, 215), "beacon": (255, 70, 50), "headlight": (255, 250, 225), "hill": (28, 32, 52),
    "farbuilding": (36, 40, 60),
}


def _colour(shape: _Shape, cond: str) -> tuple[int, int, int]:
    role, rgb, u = shape.role, shape.rgb, shape.u
    if cond == "day":
        if role == "shade":
            return tuple(int(c * 0.78) for c in rgb)  # type: ignore[return-value]
        if role == "glass":
            return _mix(rgb, (235, 240, 245), 0.25 * u)
        return rgb
    if cond == "night":
        if role in _NIGHT_FIXED:
            return _NIGHT_FIXED[role]
        if role in ("window", "glass", "blind"):
            if u < 0.5:  # lit: warm, brightness varies with u
                return _mix((200, 160, 96), (240, 214, 160), 2 * u)
            return (18, 20, 34)
        if role in ("sign", "billboard", "clock"):
            return _mix(rgb, (255, 255, 255), 0.1) if u < 0.5 else _night_dark(rgb)
        if role == "shade":
            return _night_dark(tuple(int(c * 0.9) for c in rgb))
        return _night_dark(rgb)
    # snow: overcast, so no sun shading; white ground and roofs; desaturated everything else
    if role in _SNOW_WHITE:
        return _SNOW_WHITE[role]
    if role == "foliage":
        return _mix(_snow_desat(rgb), (238, 240, 244), 0.55)
    if role == "farbuilding":
        return (196, 198, 204)
    return _snow_desat(rgb)


_SKY_GRADIENT = {  # (top, horizon)
    "day": ((118, 168, 230), (214, 230, 248)),
    "night": ((40, 44, 72), (98, 86, 102)),
    "snow": ((168, 172, 180), (212, 214, 218)),
}


def _render_layer(layer: _Layer, cond: str) -> Image.Image:
    """One layer in one condition: RGBA, ``width`` x ``_PANO_H``, alpha 0 or 255."""
    if layer.name == "sky":
        top, horizon = (np.array(c, dtype=np.float32) for c in _SKY_GRADIENT[cond])
        t = np.clip(np.arange(_PANO_H, dtype=np.float32) / _GROUND_Y, 0, 1)[:, None]
        column = np.round(top * (1 - t) + horizon * t).astype(np.uint8)
        rgba = np.concatenate([column, np.full((_PANO_H, 1), 255, np.uint8)], axis=1)
        img = Image.fromarray(np.ascontiguousarray(np.broadcast_to(rgba[:, None, :], (_PANO_H, layer.width, 4))), "RGBA")
    else:
        img = Image.new("RGBA", (layer.width, _PANO_H), (0, 0, 0, 0))
    draw = ImageDraw.Draw(img)
    for s in layer.shapes:
        if s.conds is not None and cond not in s.conds:
            continue
        fill = _colour(s, cond) + (255,)
        if s.kind == "rect":
            draw.rectangle(s.xy, fill=fill)
        elif s.kind == "poly":
            draw.polygon(s.xy, fill=fill)
        elif s.kind == "ellipse":
            draw.ellipse(s.xy, fill=fill)
        else:
            draw.line(s.xy, fill=fill, width=s.width)
    return img


def _lamp_glow(lamps, width: int) -> np.ndarray:
    """``(_PANO_H, width, 3)`` uint8 light added at night around lamp heads and their pools,
    in street-layer pixels."""
    light = np.zeros((_PANO_H, width, 3), np.float32)
    warm = np.array((1.0, 0.86, 0.6), np.float32)
    yy = np.arange(_PANO_H, dtype=np.float32)[:, None]
    for lx, ly in lamps:
        x0, x1 = max(0, lx - 100), min(width, lx + 100)
        xx = np.arange(x0, x1, dtype=np.float32)[None, :]
        head = np.exp(-((xx - lx) ** 2 + (yy - ly) ** 2) / (2 * 16.0**2))
        pool = np.exp(-((xx - lx) ** 2) / (2 * 34.0**2) - ((yy - _KERB_Y - 4) ** 2) / (2 * 10.0**2))
        light[:, x0:x1] += (50 * head + 28 * pool)[..., None] * warm
    return np.clip(np.round(light), 0, 255).astype(np.uint8)


def render_frames(seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> Iterator[tuple[str, int, np.ndarray]]:
    """Yield ``(traversal, frame, image)`` for every frame of the demo route, traversal-major.

    ``image`` is ``(240, 320, 3)`` uint8 RGB. Pure and deterministic in ``seed``: the same
    seed yields the same pixels on any machine with the same NumPy and Pillow.
    """
    seed, n_frames = _check_params(seed, n_frames)
    scene = _scene(seed, n_frames)
    fw, fh = FRAME_SIZE
    street_width = next(layer.width for layer in scene.layers if layer.name == "street")
    for ci, cond in enumerate(DEMO_TRAVERSALS):
        layers = [(_PARALLAX[layer.name], _render_layer(layer, cond)) for layer in scene.layers]
        glow = _lamp_glow(scene.lamps, street_width) if cond == "night" else None
        ox, oy = _COND_OFFSET[cond]
        for f in range(n_frames):
            rng = np.random.default_rng([seed, 100 + ci, f])
            dx, dy = rng.uniform(-4, 4), rng.uniform(-3, 3)
            zoom = rng.uniform(0.96, 1.04)
            vw, vh = int(round(fw * zoom)), int(round(fh * zoom))
            cam = f * _STEP + ox + dx
            top = int(np.clip(round((_PANO_H - vh) / 2 + oy + dy), 0, _PANO_H - vh))
            view = None
            for parallax, layer_img in layers:
                left = int(round(_X0 + parallax * cam - vw / 2))
                crop = layer_img.crop((left, top, left + vw, top + vh))
                view = crop if view is None else Image.alpha_composite(view, crop)
            image = np.asarray(view.convert("RGB"))
            if glow is not None:
                left = int(round(_X0 + _PARALLAX["street"] * cam - vw / 2))
                lit = image.astype(np.uint16) + glow[top : top + vh, left : left + vw]
                image = np.minimum(lit, 255).astype(np.uint8)
            if (vw, vh) != (fw, fh):
                image = np.asarray(Image.fromarray(image).resize((fw, fh), Image.Resampling.BILINEAR))
            yield cond, f, _finish(image, cond, rng)


def _finish(image: np.ndarray, cond: str, rng: np.random.Generator) -> np.ndarray:
    """Per-frame exposure, sensor noise and weather on a ``(240, 320, 3)`` uint8 image."""
    gain = np.float32(rng.uniform(0.94, 1.06))
    out = image.astype(np.float32)
    if cond == "night":
        out *= gain * np.float32(0.85)
        out += np.float32(6)
        # Luma noise in 2x2 blocks: looks like a dark, demosaiced frame and keeps the PNGs small.
        h, w = out.shape[:2]
        noise = rng.standard_normal(size=((h + 1) // 2, (w + 1) // 2), dtype=np.float32) * np.float32(5)
        out += np.repeat(np.repeat(noise, 2, axis=0), 2, axis=1)[:h, :w, None]
    elif cond == "snow":
        out *= gain * np.float32(0.85)
        out += np.float32(0.15 * 226)
    else:
        out *= gain
    out = np.clip(out, 0, 255, out=out).astype(np.uint8)
    if cond == "snow":
        img = Image.fromarray(out)
        draw = ImageDraw.Draw(img)
        h, w = out.shape[:2]
        n = int(rng.integers(150, 260))
        xs, ys = rng.uniform(0, w, n), rng.uniform(0, h, n)
        rs = rng.choice((0.8, 1.0, 1.0, 1.5, 2.2), size=n)
        for x, y, r in zip(xs, ys, rs):
            draw.ellipse((int(x - r), int(y - r * 1.4), int(x + r), int(y + r * 1.4)), fill=(248, 249, 252))
        out = np.asarray(img)
    return out


# --------------------------------------------------------------------------- on disk


def route_positions(seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> np.ndarray:
    """``(n_frames, 2)`` map positions ``x, y`` in ``[0, 1]`` along a gently curving route."""
    seed, n_frames = _check_params(seed, n_frames)
    rng = np.random.default_rng([seed, 99])
    t = np.linspace(0.0, 1.0, n_frames)
    amp, turns, phase = rng.uniform(0.12, 0.28), rng.uniform(0.5, 1.0), rng.uniform(0, 2 * np.pi)
    return np.stack([0.05 + 0.9 * t, 0.5 + amp * np.sin(2 * np.pi * turns * t + phase)], axis=1)


def _frame_name(f: int) -> str:
    return f"frame_{f:03d}.png"


_README_TEXT = """\
VPR Threshold Explorer: built-in demo route
===========================================

A small street drawn by vpr_explorer.data.demo (seed {seed}, {n_frames} frames, drawing version
{version}) and driven three times: day/, night/ and snow/. Frame f shows the same spot in
every traversal; neighbouring frames overlap strongly and frames ten apart do not.
positions.csv holds one map position (x,y in [0,1]) per frame.

This is a teaching route, so the app and the command line work with no download. It is
not a benchmark: numbers measured on it say nothing about real places.

route.json is written last and lists every file with its size; a folder without it
is incomplete and is regenerated. Safe to delete: it is rebuilt on demand.
"""


def write_demo_route(root: str | Path, *, seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> Path:
    """Write the demo route to ``root``: ``<traversal>/frame_###.png``, positions.csv, README.txt.

    Writes into a temporary sibling folder and moves it into place, so ``root`` is either
    absent, the previous content, or complete. An existing ``root`` is replaced only when
    it holds nothing but a (possibly damaged) demo route. Returns ``root``.
    """
    seed, n_frames = _check_params(seed, n_frames)
    root = Path(root).expanduser()
    if root.exists() and not _replaceable(root):
        raise VPRInputError(
            f"{root}: exists and holds files that are not a demo route; give a new or empty folder"
        )
    root.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(root)
    tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.tmp-", dir=root.parent))
    try:
        _write_into(tmp, seed, n_frames)
        _install(tmp, root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return root


def _write_into(folder: Path, seed: int, n_frames: int) -> None:
    sizes: dict[str, int] = {}
    for cond in DEMO_TRAVERSALS:
        (folder / cond).mkdir()
    for cond, f, image in render_frames(seed, n_frames):
        rel = f"{cond}/{_frame_name(f)}"
        _save_png(image, folder / rel)
        sizes[rel] = (folder / rel).stat().st_size
    xy = route_positions(seed, n_frames)
    text = {"encoding": "utf-8", "newline": "\n"}  # the same bytes on every platform
    (folder / POSITIONS).write_text("x,y\n" + "".join(f"{x:.6f},{y:.6f}\n" for x, y in xy), **text)
    (folder / README).write_text(_README_TEXT.format(seed=seed, n_frames=n_frames, version=DEMO_VERSION), **text)
    for name in (POSITIONS, README):
        sizes[name] = (folder / name).stat().st_size
    marker = {"seed": seed, "n_frames": n_frames, "version": DEMO_VERSION, "traversals": list(DEMO_TRAVERSALS),
              "files": sizes}
    (folder / MARKER).write_text(json.dumps(marker, indent=1, sort_keys=True) + "\n", **text)


def _save_png(image: np.ndarray, path: Path) -> None:
    # compress_level 3: nearly the size of the default at half the time.
    Image.fromarray(image).save(path, format="PNG", compress_level=3)


def _remove_stale_temporaries(root: Path, max_age_s: float = 3600.0) -> None:
    """Delete temporary siblings left by writers that were killed mid-way (an hour old or more)."""
    now = time.time()
    for p in root.parent.glob(f".{root.name}.tmp-*"):
        try:
            if now - p.stat().st_mtime > max_age_s:
                shutil.rmtree(p, ignore_errors=True)
        except OSError:
            pass  # another process removed it first


def _install(tmp: Path, root: Path) -> None:
    try:
        os.replace(tmp, root)  # also succeeds over an empty folder
        return
    except OSError:
        if not root.is_dir():
            raise
    old = root.parent / f"{tmp.name}.old"
    os.replace(root, old)
    try:
        os.replace(tmp, root)
    finally:
        shutil.rmtree(old, ignore_errors=True)


def _replaceable(root: Path) -> bool:
    """True when ``root`` is a folder holding only what a demo route holds (any part of it)."""
    if not root.is_dir():
        return False
    for entry in root.iterdir():
        if entry.name in DEMO_TRAVERSALS and entry.is_dir():
            if any(not (p.is_file() and _FRAME_NAME.match(p.name)) for p in entry.iterdir()):
                return False
        elif entry.name not in (MARKER, README, POSITIONS) or not entry.is_file():
            return False
    return True


def route_is_complete(root: str | Path, *, seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> bool:
    """True when ``root`` holds the whole route for these parameters, as its marker lists it.

    Checks the marker (written last), that every listed file exists with its listed
    size, and that each traversal holds exactly ``n_frames`` frames; reads no image.
    """
    root = Path(root)
    try:
        marker = json.loads((root / MARKER).read_text())
        files = marker["files"]
        if (marker["seed"], marker["n_frames"], marker["version"]) != (seed, n_frames, DEMO_VERSION):
            return False
        if len(files) != len(DEMO_TRAVERSALS) * n_frames + 2:
            return False
        for cond in DEMO_TRAVERSALS:
            if sum(1 for p in (root / cond).iterdir() if _FRAME_NAME.match(p.name)) != n_frames:
                return False
        return all((root / rel).stat().st_size == size for rel, size in files.items())
    except (OSError, ValueError, KeyError, TypeError):
        return False


def demo_root(seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> Path:
    """Where the demo route for these parameters lives in the cache."""
    seed, n_frames = _check_params(seed, n_frames)
    return cache_root() / "demo" / f"route-s{seed}-n{n_frames}-v{DEMO_VERSION}"


def demo_dataset(seed: int = DEMO_SEED, n_frames: int = DEMO_FRAMES) -> Dataset:
    """The demo route as a ``Dataset`` named ``demo``, written to the cache first if missing or damaged."""
    root = demo_root(seed, n_frames)
    if not route_is_complete(root, seed=seed, n_frames=n_frames):
        try:
            write_demo_route(root, seed=seed, n_frames=n_frames)
        except OSError as exc:
            # Another process may have installed the route while we drew ours.
            if not route_is_complete(root, seed=seed, n_frames=n_frames):
                raise VPRInputError(
                    f"{root}: cannot write the demo route there ({exc.strerror or exc}); set {CACHE_ENV} to a "
                    "writable folder"
                ) from exc
    return dataclasses.replace(load_dataset(root, list(DEMO_TRAVERSALS)), name="demo")
