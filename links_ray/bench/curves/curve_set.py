"""The curve set of `links bench synthesize --set`: named target curves in nine families, split
into a tuning half and a held-out half by name.

| family | what it is | closed |
|---|---|---|
| `letter_outline` | a capital's outer contour, in Liberation Sans and Liberation Serif | yes |
| `letter_stroke` | the same letters as open strokes: a run of the outline (`stroke_run`) | no |
| `gait` | a foot's path: a flat stride, a lifted return of varied height and lean | yes |
| `cam` | a cam's profile in polar form: dwells joined by cycloidal rises and returns | yes |
| `random_smooth` | a few Fourier harmonics, decaying, seeded, never crossing itself | yes |
| `self_crossing` | eights, dual loops, trefoils, hourglasses, seeded (`crossing_curves`) | yes |
| `traced` | the path of a random valid mechanism of 6-12 joints, seeded (`traced_curves`) | yes |
| `gcp_holo_test` | GCP-HOLO's eight path-synthesis test curves (`gcp_holo_curves`) | yes |
| `gcp_holo_gait` | GCP-HOLO's four walking-mechanism foot paths | yes |

The letters are read at run time from the TrueType files of the Debian package
`fonts-liberation` (with fontTools, the `bench` extra). Each curve is `CURVE_POINTS` points
evenly spaced by arc length, centred on its bounding box, the box's longer side 2. The set's
own simple closed curves run counter-clockwise; the others keep the order they were drawn,
traced or published in. No closed curve repeats its first point.

A curve's half is fixed by its name alone (`half_of`): the parity of the first byte of a
SHA-256 digest, of the letter for a letter's four curves (so no letter is seen in tuning and
held out), else of the name. GCP-HOLO's curves are the field's benchmark and are all held out:
nothing is tuned on them. Adding, dropping or reordering curves never moves another one.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from links_ray.bench.curves.crossing import crossing_curves
from links_ray.bench.curves.gcp_holo import FIELD_PREFIX, gcp_holo_curves
from links_ray.bench.curves.traced import traced_curves
from links_ray.bench.targets import TARGET_POINTS
from links_ray.engine.kinematics.paths import even_along

#: Points per curve, as for the shipped targets.
CURVE_POINTS = TARGET_POINTS
#: The two halves, by the parity of a name's digest.
HALVES = ("tuning", "held-out")
#: Capitals drawn from each font: corners, diagonals, bowls and a hole or two.
LETTERS = "ABCEGKMNRSWZ"
#: The fonts by the short name curves carry, and their files in `fonts-liberation`.
FONTS = {"sans": "LiberationSans-Regular.ttf", "serif": "LiberationSerif-Regular.ttf"}
#: Where Debian installs `fonts-liberation` (and its successor `fonts-liberation2`).
FONT_DIRS = (
    Path("/usr/share/fonts/truetype/liberation"),
    Path("/usr/share/fonts/truetype/liberation2"),
)
#: Share of the outline's length a letter's stroke runs along.
STROKE_SHARE = 0.6
#: Random smooth curves drawn, and the default seed of their generator.
RANDOM_CURVES = 10
RANDOM_SEED = 0
#: Highest harmonic of a random smooth curve, and its amplitudes' decay with the harmonic.
RANDOM_HARMONICS, RANDOM_DECAY = 5, 1.6
#: Points per Bézier segment when a glyph's contour is flattened.
BEZIER_STEPS = 24


@dataclass(frozen=True)
class SetCurve:
    """One named curve of the set: its (CURVE_POINTS, 2) points and how it is read."""

    name: str
    family: str
    partial: bool
    half: str
    points: np.ndarray


def half_of(name: str) -> str:
    """The half (`tuning` or `held-out`) a curve of this name belongs to: by the parity of the
    first byte of the SHA-256 digest of its shape's key, which for a letter's curves
    (`sans_E_outline`) is the letter (`letter E`), so that a letter is in one half in both
    fonts, outline and stroke alike, and for any other curve its name. A curve of GCP-HOLO's
    (named `holo_...`) is held out."""
    if name.startswith(FIELD_PREFIX):
        return HALVES[1]
    parts = name.split("_")
    letter = len(parts) == 3 and parts[0] in FONTS and parts[2] in ("outline", "stroke")
    key = f"letter {parts[1]}" if letter else name
    return HALVES[hashlib.sha256(key.encode()).digest()[0] % 2]


def curve_set(
    seed: int = RANDOM_SEED, font_dirs: tuple[Path, ...] = FONT_DIRS, points: int = CURVE_POINTS
) -> list[SetCurve]:
    """Every curve of the set, letters first; `seed` draws the random smooth, self-crossing and
    traced curves. Raises ValueError when a font file is not found in `font_dirs`."""
    shapes: list[tuple[str, str, bool, np.ndarray]] = []
    for font, filename in FONTS.items():
        for letter, loop in letter_outlines(font_file(filename, font_dirs)).items():
            shapes.append((f"{font}_{letter}_outline", "letter_outline", False, loop))
            shapes.append((f"{font}_{letter}_stroke", "letter_stroke", True, stroke_run(loop)))
    shapes += [(name, "gait", False, loop) for name, loop in gait_curves().items()]
    shapes += [(name, "cam", False, loop) for name, loop in cam_curves().items()]
    shapes += [(name, "random_smooth", False, loop) for name, loop in random_smooth(seed).items()]
    shapes += [(name, "self_crossing", False, loop) for name, loop in crossing_curves(seed).items()]
    shapes += [(name, "traced", False, curve.points) for name, curve in traced_curves(seed).items()]
    for family, curves in gcp_holo_curves().items():
        shapes += [(name, f"gcp_holo_{family}", False, loop) for name, loop in curves.items()]
    return [
        SetCurve(
            name, family, partial, half_of(name), _framed(even_along(line, points, not partial))
        )
        for name, family, partial, line in shapes
    ]


def font_file(filename: str, font_dirs: tuple[Path, ...] = FONT_DIRS) -> Path:
    """The path of the font `filename` in the first of `font_dirs` that holds it."""
    for folder in font_dirs:
        if (folder / filename).is_file():
            return folder / filename
    raise ValueError(
        f"font {filename} not found in {', '.join(map(str, font_dirs))}: "
        "install the Debian package fonts-liberation"
    )


def letter_outlines(path: Path) -> dict[str, np.ndarray]:
    """Each of LETTERS's outer contour in the font at `path`: a dense closed polyline,
    counter-clockwise, without its first point repeated."""
    try:
        from fontTools.pens.basePen import BasePen
        from fontTools.ttLib import TTFont
    except ImportError as error:
        raise ValueError("reading fonts needs fontTools: pip install 'links-ray[bench]'") from error

    class FlatPen(BasePen):
        """Collects a glyph's contours as polylines, its Bézier segments sampled evenly in t."""

        def __init__(self, glyphs: object) -> None:
            super().__init__(glyphs)
            self.contours: list[list[tuple[float, float]]] = []

        def _moveTo(self, pt: tuple[float, float]) -> None:
            self.contours.append([pt])

        def _lineTo(self, pt: tuple[float, float]) -> None:
            self.contours[-1].append(pt)

        def _curveToOne(self, p1: tuple, p2: tuple, p3: tuple) -> None:
            p0 = np.array(self._getCurrentPoint(), float)
            t = np.linspace(0, 1, BEZIER_STEPS + 1)[1:, None]
            a, b, c = np.array(p1, float), np.array(p2, float), np.array(p3, float)
            curve = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * a + 3 * (1 - t) * t**2 * b
            self.contours[-1] += [tuple(p) for p in curve + t**3 * c]

        def _qCurveToOne(self, p1: tuple, p2: tuple) -> None:
            p0 = np.array(self._getCurrentPoint(), float)
            t = np.linspace(0, 1, BEZIER_STEPS + 1)[1:, None]
            a, b = np.array(p1, float), np.array(p2, float)
            curve = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * a + t**2 * b
            self.contours[-1] += [tuple(p) for p in curve]

    font = TTFont(str(path))
    glyphs, cmap = font.getGlyphSet(), font.getBestCmap()
    outlines = {}
    for letter in LETTERS:
        pen = FlatPen(glyphs)
        glyphs[cmap[ord(letter)]].draw(pen)
        loops = [np.array(contour, float) for contour in pen.contours if len(contour) > 2]
        outer = max(loops, key=lambda loop: abs(_area(loop)))
        if np.allclose(outer[0], outer[-1]):
            outer = outer[:-1]
        outlines[letter] = outer if _area(outer) > 0 else outer[::-1]
    return outlines


def stroke_run(loop: np.ndarray) -> np.ndarray:
    """A letter's open stroke: the run of its counter-clockwise outline `loop` that starts at
    the point nearest the bottom-left corner of its box and covers STROKE_SHARE of its length,
    as a dense open polyline."""
    start = int(np.argmin(np.linalg.norm(loop - loop.min(axis=0), axis=1)))
    around = np.concatenate([np.roll(loop, -start, axis=0), loop[start : start + 1]])
    return even_along(around, 4 * len(around), closed=False, share=STROKE_SHARE)


def gait_curves() -> dict[str, np.ndarray]:
    """Feet paths: a flat stride from (-1, 0) to (1, 0) on the ground, then a return arc
    lifted to `height`, its shape `sin^power`, shifted along x by `lean` times its lift."""
    kinds = {
        "gait_low": (0.25, 1.0, 0.0),
        "gait_high": (0.6, 1.0, 0.0),
        "gait_flat_top": (0.4, 0.4, 0.0),
        "gait_peaked": (0.45, 2.0, 0.0),
        "gait_lean": (0.4, 1.0, 0.5),
        "gait_lean_back": (0.35, 0.6, -0.4),
    }
    u = np.linspace(0, 1, 400, endpoint=False)
    curves = {}
    for name, (height, power, lean) in kinds.items():
        stride = np.column_stack([2 * u - 1, np.zeros_like(u)])
        lift = height * np.sin(np.pi * u) ** power
        arc = np.column_stack([np.cos(np.pi * u) + lean * lift, lift])
        curves[name] = np.concatenate([stride, arc])
    return curves


def cam_curves() -> dict[str, np.ndarray]:
    """Cam profiles r(θ) = 1 + lift · s(θ): s rises 0 to 1 and returns, each with cycloidal
    motion, between dwells; (rise, dwell high, return) as shares of a turn, the rest a low
    dwell."""
    kinds = {
        "cam_eccentric": (0.5, 0.0, 0.5, 0.5),
        "cam_dwell": (0.3, 0.2, 0.3, 0.6),
        "cam_quick_return": (0.5, 0.1, 0.15, 0.5),
        "cam_long_dwell": (0.2, 0.45, 0.2, 0.4),
        "cam_high_lift": (0.35, 0.15, 0.35, 0.9),
        "cam_short": (0.2, 0.05, 0.2, 0.35),
    }
    theta = np.linspace(0, 2 * np.pi, 800, endpoint=False)
    share = theta / (2 * np.pi)
    curves = {}
    for name, (rise, high, fall, lift) in kinds.items():
        up = np.clip(share / rise, 0, 1)
        down = np.clip((share - rise - high) / fall, 0, 1)
        s = _cycloidal(up) - _cycloidal(down)
        radius = 1 + lift * s
        curves[name] = np.column_stack([radius * np.cos(theta), radius * np.sin(theta)])
    return curves


def random_smooth(seed: int = RANDOM_SEED, count: int = RANDOM_CURVES) -> dict[str, np.ndarray]:
    """`count` random smooth closed curves z(t) = e^{it} + Σ c_k e^{ikt} over harmonics
    k = ±2..±RANDOM_HARMONICS (and k = -1), c_k complex normal scaled by 0.5 / |k|^RANDOM_DECAY,
    drawn from `seed` and redrawn while the curve crosses itself; counter-clockwise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    harmonics = np.array(
        [k for k in range(-RANDOM_HARMONICS, RANDOM_HARMONICS + 1) if k not in (0, 1)]
    )
    scale = 0.5 / np.abs(harmonics) ** RANDOM_DECAY
    curves = {}
    while len(curves) < count:
        c = scale * (rng.normal(size=len(harmonics)) + 1j * rng.normal(size=len(harmonics)))
        z = np.exp(1j * t) + np.exp(1j * np.outer(t, harmonics)) @ c
        loop = np.column_stack([z.real, z.imag])
        if _area(loop) > 0 and not crosses_itself(loop):
            curves[f"random_{len(curves):02d}"] = loop
    return curves


def crosses_itself(loop: np.ndarray) -> bool:
    """Whether the closed polyline `loop` has two non-adjacent segments that touch (collinear
    ones count as touching: the random curves have no straight runs to trip on)."""
    a, b = loop, np.roll(loop, -1, axis=0)
    n = len(loop)
    i, j = np.triu_indices(n, 2)
    keep = (j - i) % n != n - 1  # the first and last segments share a point
    i, j = i[keep], j[keep]

    def side(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.sign(
            (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])
        )

    d1 = side(a[i], b[i], a[j])
    d2 = side(a[i], b[i], b[j])
    d3 = side(a[j], b[j], a[i])
    d4 = side(a[j], b[j], b[i])
    return bool(np.any((d1 * d2 <= 0) & (d3 * d4 <= 0)))


def _cycloidal(x: np.ndarray) -> np.ndarray:
    """Cycloidal motion from 0 to 1 over x in [0, 1]: no speed or acceleration at either end."""
    return x - np.sin(2 * np.pi * x) / (2 * np.pi)


def _area(loop: np.ndarray) -> float:
    """Signed area of the closed polyline `loop` (positive counter-clockwise)."""
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _framed(points: np.ndarray) -> np.ndarray:
    """`points` centred on their bounding box, scaled so the box's longer side is 2."""
    low, high = points.min(axis=0), points.max(axis=0)
    return (points - (low + high) / 2) * (2 / float(np.max(high - low)))
