"""Procedural "solid" textures of the synthetic subject, evaluated per sample.

Every material is a function of the canonical (zero-pose, T-pose) surface position in SMPL axes
(x the body's left, y up, z forward, metres) and a few landmarks, so the texture sticks to the body
and never depends on Anny's UV layout. All functions take arrays of M samples and return albedo
``[M,3]`` float32 in 0..1 (sRGB-ish; the renderer shades it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Material ids (per face).
SKIN, HEAD, EYE, MOUTH, UNDERSHIRT, TROUSERS, SHOES, TUNIC, HAIR, LASH = range(10)
MATERIALS = ("skin", "head", "eye", "mouth", "undershirt", "trousers", "shoes", "tunic", "hair", "lash")


@dataclass
class Palette:
    """The subject's colours (RGB 0..1); the seed picks one."""

    skin: np.ndarray
    hair: np.ndarray
    iris: np.ndarray
    lips: np.ndarray
    tunic: np.ndarray
    tunic_stripe: np.ndarray
    tunic_trim: np.ndarray
    print_: np.ndarray
    trousers: np.ndarray
    shoes: np.ndarray


def make_palette(rng: np.random.Generator) -> Palette:
    """A plausible outfit: colours drawn from small curated sets so every seed looks like clothing."""
    c = lambda *v: np.asarray(v, dtype=np.float32)  # noqa: E731
    skins = [c(0.93, 0.76, 0.64), c(0.80, 0.60, 0.46), c(0.62, 0.43, 0.31), c(0.45, 0.30, 0.21)]
    hairs = [c(0.10, 0.07, 0.05), c(0.28, 0.17, 0.09), c(0.55, 0.38, 0.20), c(0.05, 0.05, 0.06)]
    irises = [c(0.25, 0.15, 0.08), c(0.20, 0.35, 0.55), c(0.25, 0.40, 0.25)]
    tunics = [
        (c(0.70, 0.12, 0.14), c(0.95, 0.90, 0.80), c(0.15, 0.12, 0.20)),
        (c(0.10, 0.42, 0.45), c(0.98, 0.85, 0.45), c(0.08, 0.12, 0.16)),
        (c(0.92, 0.62, 0.10), c(0.15, 0.20, 0.45), c(0.30, 0.12, 0.08)),
        (c(0.30, 0.25, 0.55), c(0.92, 0.92, 0.88), c(0.85, 0.30, 0.25)),
    ]
    prints = [c(0.98, 0.97, 0.93), c(0.10, 0.10, 0.12), c(0.95, 0.80, 0.20)]
    trousers = [c(0.16, 0.24, 0.42), c(0.22, 0.22, 0.24), c(0.45, 0.38, 0.26), c(0.12, 0.28, 0.22)]
    shoes = [c(0.32, 0.18, 0.10), c(0.08, 0.08, 0.09), c(0.85, 0.85, 0.82)]
    pick = lambda seq: seq[int(rng.integers(len(seq)))]  # noqa: E731
    tunic, stripe, trim = pick(tunics)
    return Palette(pick(skins), pick(hairs), pick(irises), c(0.66, 0.36, 0.36), tunic, stripe, trim,
                   pick(prints), pick(trousers), pick(shoes))


# ----------------------------------------------------------------------------------------------------
# noise


def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice -> uniform [0,1) (a 32-bit integer hash; deterministic on every platform)."""
    h = (ix.astype(np.uint32) * np.uint32(0x8DA6B343)) ^ (iy.astype(np.uint32) * np.uint32(0xD8163841))
    h ^= iz.astype(np.uint32) * np.uint32(0xCB1AB31F)
    h ^= np.uint32(seed * 0x9E3779B1 & 0xFFFFFFFF)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return h.astype(np.float32) / np.float32(4294967296.0)


def value_noise(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth 3D value noise in [0,1] at points ``p [M,3]`` (lattice spacing 1)."""
    with np.errstate(over="ignore"):
        f = np.floor(p)
        t = p - f
        t = t * t * (3 - 2 * t)
        i = f.astype(np.int64)
        out = np.zeros(len(p), dtype=np.float32)
        for dx in (0, 1):
            wx = t[:, 0] if dx else 1 - t[:, 0]
            for dy in (0, 1):
                wy = t[:, 1] if dy else 1 - t[:, 1]
                for dz in (0, 1):
                    wz = t[:, 2] if dz else 1 - t[:, 2]
                    out += wx * wy * wz * _hash(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def fbm(p: np.ndarray, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise, normalised to about [0,1]."""
    total = np.zeros(len(p), dtype=np.float32)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(p * (2.0**o), seed + 17 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Blend colours ``a`` and ``b`` ([3] or [M,3]) with weights ``t [M]``."""
    return a + (b - a) * t[:, None]


def _band(x: np.ndarray, centre, half_width, soft: float) -> np.ndarray:
    """1 inside |x - centre| < half_width, fading to 0 over ``soft``."""
    return 1.0 - smoothstep(half_width, half_width + soft, np.abs(x - centre))


# ----------------------------------------------------------------------------------------------------
# materials. ``q`` [M,3] canonical position; ``aux`` [M,3] extra per-vertex data (see subject.py):
# for limbs and the torso the unit radial direction from the nearest bone axis.


@dataclass
class Landmarks:
    """Canonical positions the textures are laid out from (SMPL axes, metres)."""

    eye_l: np.ndarray
    eye_r: np.ndarray
    eye_radius: float
    mouth: np.ndarray
    head_centre: np.ndarray
    neck_y: float
    neck: np.ndarray
    pelvis: np.ndarray
    hem_y: float
    waist_y: float
    chest: np.ndarray
    ground_y: float
    foot_x: float


def skin(q: np.ndarray, pal: Palette, seed: int) -> np.ndarray:
    n = fbm(q * 60.0, 2, seed + 1)
    return pal.skin[None] * (0.92 + 0.12 * n[:, None])


def head(q: np.ndarray, lm: Landmarks, pal: Palette, seed: int) -> np.ndarray:
    """Face features painted on the head: hair, brows, eyelids, lips, cheeks, nose shading."""
    col = skin(q, pal, seed)
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    cx = 0.5 * (lm.eye_l[0] + lm.eye_r[0])
    eye_y = 0.5 * (lm.eye_l[1] + lm.eye_r[1])
    front = z - lm.head_centre[2]
    dx = x - cx
    # Hair: above a hairline that is high on the forehead and drops to the nape at the back.
    ang = np.arctan2(dx, front)  # 0 = facing forward
    hairline = eye_y + 0.055 - 0.07 * smoothstep(0.6, 2.2, np.abs(ang)) + 0.012 * np.cos(6 * ang)
    hair_t = smoothstep(-0.004, 0.004, y - hairline)
    strands = fbm(np.stack([x * 260.0, y * 25.0, z * 260.0], 1), 3, seed + 2)
    hair = pal.hair[None] * (0.65 + 0.7 * strands[:, None])
    # Cheeks and nose: slight redness, shadow at the nose sides.
    cheek = np.exp(-((np.abs(dx) - 0.045) ** 2 + (y - (eye_y - 0.035)) ** 2) / (2 * 0.015**2)) * (front > 0)
    col = _mix(col, pal.skin * np.array([1.0, 0.75, 0.72], np.float32), 0.35 * cheek)
    nose_side = np.exp(-((np.abs(dx) - 0.017) ** 2) / (2 * 0.005**2) - (y - (eye_y - 0.03)) ** 2 / (2 * 0.015**2))
    col *= (1 - 0.25 * nose_side * (front > 0))[:, None]
    for eye in (lm.eye_l, lm.eye_r):
        ex, ey = x - eye[0], y - eye[1]
        # Brow: an arc above the eye, thicker at the inner end.
        inner = np.sign(eye[0] - cx) * ex < 0
        brow_y = eye[1] + 0.019 + 0.004 * (1 - (ex / 0.022) ** 2)
        brow = _band(y, brow_y, np.where(inner, 0.0034, 0.0024), 0.001) * _band(ex, 0.0, 0.02, 0.003)
        brow *= front > 0.02
        hairs = 0.7 + 0.3 * fbm(np.stack([x * 900.0, y * 120.0, z * 10.0], 1), 1, seed + 3)
        col = _mix(col, pal.hair * 0.8 * hairs[:, None], 0.9 * brow)
        # Upper-lid crease and a soft shadow in the eye socket.
        ellipse = np.sqrt((ex / 0.017) ** 2 + (ey / 0.010) ** 2)
        crease = _band(ellipse, 1.0, 0.06, 0.12) * (ey > 0.002) * (front > 0.02)
        col *= (1 - 0.3 * crease)[:, None]
        socket = (1 - smoothstep(0.8, 1.3, ellipse)) * (front > 0.02)
        col *= (1 - 0.12 * socket)[:, None]
    # Lips: an upper and a lower lobe around the mouth, a dark line between.
    mx, my = x - lm.mouth[0], y - lm.mouth[1]
    lip_shape = (mx / 0.024) ** 2 + (my / 0.0085) ** 2
    lips = (1 - smoothstep(0.8, 1.1, lip_shape)) * (front > 0.03)
    col = _mix(col, pal.lips, 0.85 * lips)
    seam = _band(my, 0.0012 * np.cos(mx / 0.024 * np.pi), 0.0007, 0.0007) * (lip_shape < 1.0) * (front > 0.03)
    col = _mix(col, np.array([0.25, 0.08, 0.08], np.float32), 0.9 * seam)
    return _mix(col, hair, hair_t)


def eye(q: np.ndarray, centre: np.ndarray, pal: Palette) -> np.ndarray:
    """Eyeball: sclera, iris (with radial streaks) and pupil, looking forward (+z)."""
    d = q - centre[None]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    ang = np.arccos(np.clip(d[:, 2], -1, 1))  # angle from the gaze direction
    col = np.broadcast_to(np.array([0.93, 0.91, 0.88], np.float32), (len(q), 3)).copy()
    streak = 0.8 + 0.2 * np.cos(np.arctan2(d[:, 1], d[:, 0]) * 23)
    col = _mix(col, pal.iris * streak[:, None], 1 - smoothstep(0.50, 0.56, ang))
    return _mix(col, np.zeros(3, np.float32), 1 - smoothstep(0.20, 0.25, ang))


def neck_hole(q: np.ndarray, neck: np.ndarray) -> np.ndarray:
    """Signed field of the tunic's neckline (the same cut as the garment's): > 0 inside the neck hole."""
    dx = (q[:, 0] - neck[0]) / 0.075
    dz = np.clip(q[:, 2] - neck[2], 0.0, None) / 0.10
    outside = (np.sqrt(dx**2 + dz**2) - 1.0) * 0.07
    front = np.clip((q[:, 2] - neck[2]) / 0.08, 0.0, 1.0)
    below = (neck[1] - 0.015 - 0.085 * front**2) - q[:, 1]
    return -np.maximum(outside, below)


def undershirt(q: np.ndarray, lm: "Landmarks", pal: Palette, seed: int) -> np.ndarray:
    """The body under the tunic (seen through the openings): dark, skin inside the neck hole."""
    n = fbm(q * 80.0, 2, seed + 4)
    col = pal.tunic[None] * (0.45 + 0.15 * n[:, None])
    return _mix(col, skin(q, pal, seed), smoothstep(-0.006, 0.0, neck_hole(q, lm.neck)))


def trousers(q: np.ndarray, aux: np.ndarray, lm: Landmarks, pal: Palette, seed: int) -> np.ndarray:
    """Denim-like twill with fading, outer side seams with stitching, a waistband and a fly seam."""
    x, y = q[:, 0], q[:, 1]
    twill = 0.5 + 0.5 * np.sin((y * 1.0 + np.abs(x) * 0.6 + q[:, 2] * 0.6) * 2 * np.pi / 0.004)
    fade = fbm(q * np.array([8.0, 3.0, 8.0], np.float32), 3, seed + 5)
    col = pal.trousers[None] * (0.78 + 0.18 * twill[:, None] + 0.35 * (fade[:, None] - 0.5))
    side = np.sign(x)
    lateral = aux[:, 0] * side  # radial direction from the leg axis, towards the body's outside
    seam = _band(lateral, 1.0, 0.04, 0.04)
    col *= (1 - 0.35 * seam)[:, None]
    stitch_pos = np.abs(np.arcsin(np.clip(aux[:, 2], -1, 1)))
    dashes = (np.sin(y * 2 * np.pi / 0.012) > 0.0).astype(np.float32)
    stitch = _band(stitch_pos, 0.16, 0.02, 0.02) * (lateral > 0.8) * dashes
    col = _mix(col, np.array([0.85, 0.62, 0.25], np.float32), 0.8 * stitch)
    # Waistband just below the tunic's hem line (visible when the hem swings), and a front fly seam.
    band = _band(y, lm.hem_y + 0.012, 0.012, 0.004)
    col *= (1 - 0.2 * band)[:, None]
    fly = _band(x - lm.pelvis[0], 0.0, 0.002, 0.002) * (q[:, 2] > lm.pelvis[2]) * (y > lm.hem_y - 0.16)
    col *= (1 - 0.45 * fly)[:, None]
    hem = _band(y, lm.ground_y + 0.10, 0.008, 0.003)
    return col * (1 - 0.3 * hem)[:, None]


def shoes(q: np.ndarray, lm: Landmarks, pal: Palette, seed: int) -> np.ndarray:
    """Leather upper with laces on the instep and a light rubber sole."""
    y = q[:, 1]
    n = fbm(q * 120.0, 2, seed + 6)
    col = pal.shoes[None] * (0.85 + 0.25 * n[:, None])
    sole = 1 - smoothstep(lm.ground_y + 0.022, lm.ground_y + 0.028, y)
    col = _mix(col, np.array([0.92, 0.90, 0.86], np.float32), sole)
    # Laces: short bars across the instep, on the front of the foot above the sole.
    instep = (q[:, 2] > lm.pelvis[2] + 0.03) & (y > lm.ground_y + 0.04) & (y < lm.ground_y + 0.09)
    bars = _band(np.mod(y - lm.ground_y, 0.012), 0.006, 0.0015, 0.001)
    foot_x = np.abs(q[:, 0] - lm.pelvis[0])
    centre = _band(foot_x, lm.foot_x, 0.012, 0.004)
    col = _mix(col, np.array([0.9, 0.88, 0.85], np.float32), 0.9 * bars * centre * instep)
    return col


def tunic(q: np.ndarray, aux: np.ndarray, hem_w: np.ndarray, lm: Landmarks, pal: Palette,
          seed: int, inside: np.ndarray) -> np.ndarray:
    """The loose top: woven texture, a chest print, horizontal stripes on the skirt part, side and
    shoulder seams with stitching, a contrasting hem band and sleeve cuffs. ``hem_w`` is 0 at the waist
    and 1 at the hem; ``inside`` marks samples seen from the garment's inner side (lining)."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    weave = 0.5 + 0.25 * (np.sin(x * 2 * np.pi / 0.003) + np.sin(y * 2 * np.pi / 0.003))
    blotch = fbm(q * 20.0, 3, seed + 7)
    col = pal.tunic[None] * (0.86 + 0.12 * weave[:, None] + 0.2 * (blotch[:, None] - 0.5))
    # Stripes on the lower part, two widths.
    stripe_y = y - lm.hem_y
    stripes = _band(np.mod(stripe_y, 0.06), 0.03, 0.010, 0.002) * (stripe_y < 0.20)
    thin = _band(np.mod(stripe_y + 0.03, 0.06), 0.03, 0.002, 0.001) * (stripe_y < 0.20)
    col = _mix(col, pal.tunic_stripe, stripes)
    col = _mix(col, pal.tunic_trim, thin)
    # A print on the chest: a ring with a star, only on the front.
    front = z > lm.chest[2] - 0.03
    px, py = x - lm.chest[0], y - lm.chest[1]
    r = np.sqrt(px**2 + py**2)
    ring = _band(r, 0.055, 0.006, 0.002)
    theta = np.arctan2(py, px)
    star_r = 0.042 * (0.55 + 0.45 * np.cos(5 * theta) ** 2)
    star = 1 - smoothstep(star_r - 0.002, star_r + 0.002, r)
    logo = np.maximum(ring, star) * front
    col = _mix(col, pal.print_, 0.95 * logo)
    # Side seams (radial direction lateral), shoulder seams, with dashed stitches beside them.
    lateral = np.abs(aux[:, 0])
    below_arm = y < lm.chest[1] + 0.03
    seam = _band(lateral, 1.0, 0.03, 0.02) * below_arm
    col *= (1 - 0.4 * seam)[:, None]
    dashes = (np.sin(y * 2 * np.pi / 0.01) > 0).astype(np.float32)
    stitch = _band(lateral, 0.985, 0.004, 0.003) * dashes * below_arm
    col = _mix(col, pal.tunic_stripe, 0.7 * stitch)
    # Hem band and its stitch line; sleeve cuffs (arm samples: |x| beyond the torso).
    band = smoothstep(0.86, 0.92, hem_w)
    col = _mix(col, pal.tunic_trim, band)
    hem_stitch = _band(hem_w, 0.89, 0.006, 0.004) * (np.sin((x + z) * 2 * np.pi / 0.01) > 0)
    col = _mix(col, pal.tunic_stripe, 0.8 * hem_stitch)
    lining = pal.tunic * 0.45
    return np.where(inside[:, None], lining[None], col)


def hair_shell(q: np.ndarray, pal: Palette, seed: int) -> np.ndarray:
    strands = fbm(np.stack([q[:, 0] * 300.0, q[:, 1] * 30.0, q[:, 2] * 300.0], 1), 3, seed + 8)
    return pal.hair[None] * (0.6 + 0.8 * strands[:, None])
