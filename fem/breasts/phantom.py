"""Virtual patients: labelled breast volumes with the metadata the FE step needs.

Every patient is a pure function of ``(seed, patient index)``; each breast of a patient is a
pure function of ``(seed, patient index, laterality)``, so breasts can be generated in any
order, in parallel, and regenerated identically. The distributions and their sources are
documented in ``docs/cohort.md``.

Anatomy, in the breast's local frame (u lateral, v anterior, w superior; mm):

* the chest wall is the curved surface ``v = v_cw(u)`` of a torso of radius ``R``;
* the pectoral muscle is a layer of thickness ``t_m`` behind it, under the breast base;
* the breast is the set ``0 <= d <= p`` (``d = v - v_cw(u)`` the depth from the chest wall)
  whose cross-section at depth ``d`` is an ellipse of half-axes ``a_u r(d), a_w r(d)`` with
  profile ``r(d) = (1 - (d/p)^q)^(1/q)``, a boundary ripple of low angular order, and a
  centre that sags (ptosis) and turns laterally as ``(d/p)^2``. The map ``(u, d, w) ->
  (u, v, w)`` is a shear, so the volume is ``a_u a_w p C(q) W`` in closed form;
* fibroglandular tissue is the upper quantile of a smooth Gaussian random field plus a
  retroareolar bias (denser behind the nipple), kept out of the subcutaneous and
  retromammary fat, with the quantile chosen to hit the sampled glandular fraction.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import integrate, ndimage

from fem.contract.trajectory import Tissue

DENSITY_CATEGORIES = ("a", "b", "c", "d")


@dataclass(frozen=True)
class LabelVolume:
    """A labelled image: canonical `Tissue` labels on a voxel grid.

    Attributes
    ----------
    labels : (I, J, K) uint8
        `Tissue` value of each voxel.
    affine : (4, 4) float64
        Voxel index (i, j, k, 1) -> RAS+ patient coordinates in mm (as NIfTI's affine).
    source : str
        Where the volume came from (a file path or a phantom id), used in error messages.
    """

    labels: NDArray[np.uint8]
    affine: NDArray[np.float64]
    source: str = "volume"

    @property
    def spacing(self) -> NDArray[np.float64]:
        """(3,) voxel edge lengths in mm."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel in mm^3."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    def tissue_volume(self, *tissues: Tissue) -> float:
        """Total volume of the voxels carrying any of ``tissues``, mm^3."""
        return float(np.isin(self.labels, tissues).sum()) * self.voxel_volume


@dataclass(frozen=True)
class Site:
    """Population of one clinical site (distribution parameters; see docs/cohort.md)."""

    name: str
    fraction: float  #: share of the cohort's patients
    age_range: tuple[float, float]  #: years
    age_mean: float
    age_sd: float
    volume_median_cm3: float  #: median breast volume (log-normal)
    volume_sigma: float  #: log-space standard deviation
    density_probabilities: tuple[float, float, float, float]  #: BI-RADS a, b, c, d
    compression_mean: float  #: mean of the compression ratio's normal part
    compression_sd: float  #: its standard deviation


#: Two sites echoing the reference paper's cohort (26 Vienna + 232 Jena patients, ~10 / 90 %).
SITES = (
    Site("A", 0.10, (29, 78), 52, 11, 520.0, 0.50, (0.06, 0.34, 0.44, 0.16), 0.42, 0.10),
    Site("B", 0.90, (23, 92), 57, 12, 620.0, 0.55, (0.10, 0.43, 0.39, 0.08), 0.46, 0.09),
)

#: Volumetric glandular fraction range of each BI-RADS density category (Volpara density
#: grade thresholds 3.5 / 7.5 / 15.5 %, see docs/cohort.md).
DENSITY_RANGES = {"a": (0.015, 0.035), "b": (0.035, 0.075), "c": (0.075, 0.155), "d": (0.155, 0.35)}

VOLUME_RANGE_CM3 = (100.0, 2500.0)
#: Support of the compression ratio. The paper's cohort reached 76 %; the support ends a little
#: above so that a finite cohort's largest sampled ratio does too (516 breasts: 76.4 %).
COMPRESSION_RANGE = (0.05, 0.775)


def density_category(glandular_fraction: float) -> str:
    """BI-RADS category (a-d) of a volumetric glandular fraction."""
    for cat in DENSITY_CATEGORIES[:-1]:
        if glandular_fraction < DENSITY_RANGES[cat][1]:
            return cat
    return "d"


@dataclass(frozen=True)
class BreastShape:
    """Sampled parameters of one breast (lengths in mm)."""

    laterality: str  #: "L" or "R"
    target_volume_cm3: float
    a_u: float  #: base half-width, medial-lateral
    a_w: float  #: base half-height, cranio-caudal
    projection: float  #: anterior extent p
    profile_q: float  #: profile exponent q (2: ellipsoid, < 2 conical, > 2 full)
    ptosis: float  #: nipple drop as a fraction of a_w
    lateral_turn: float  #: nipple lateral shift as a fraction of a_u
    ripple: tuple[tuple[float, float], ...]  #: (amplitude, phase) of angular orders 2, 3, 4
    muscle_thickness: float
    chest_radius: float
    midline_offset: float  #: distance of the base centre from the sternum midline
    glandular_fraction: float
    gland_length: float  #: correlation length of the glandular field
    gland_bias: float  #: strength of the retroareolar bias
    subcutaneous_fat: float  #: gland-free layer under the skin
    retromammary_fat: float  #: gland-free layer in front of the muscle
    compression_ratio: float


GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0

#: Share of the compression-ratio distribution spread uniformly over `COMPRESSION_RANGE`
#: (the rest is the site's truncated normal): the rare very light and very firm compressions.
COMPRESSION_TAIL = 0.12


def compression_quantile(site: Site, u: float) -> float:
    """Inverse CDF of a site's compression-ratio distribution at quantile ``u``.

    The distribution is ``(1 - COMPRESSION_TAIL)`` truncated normal (the site's mean and
    standard deviation) plus ``COMPRESSION_TAIL`` uniform, both on `COMPRESSION_RANGE`.
    """
    x = np.linspace(*COMPRESSION_RANGE, 2001)
    normal = np.exp(-0.5 * ((x - site.compression_mean) / site.compression_sd) ** 2)
    pdf = (1 - COMPRESSION_TAIL) * normal / np.trapezoid(normal, x) + COMPRESSION_TAIL / (
        x[-1] - x[0]
    )
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(x))])
    return float(np.interp(u, cdf / cdf[-1], x))


def _truncated_normal(
    rng: np.random.Generator, mean: float, sd: float, lo: float, hi: float
) -> float:
    while True:
        x = rng.normal(mean, sd)
        if lo <= x <= hi:
            return float(x)


def _reflect(x: float, lo: float, hi: float) -> float:
    """Fold ``x`` into ``[lo, hi]`` by mirroring at the bounds (clipping would pile values up there)."""
    w = hi - lo
    y = (x - lo) % (2 * w)
    return float(lo + (y if y <= w else 2 * w - y))


def profile_area_factor(q: float) -> float:
    """``C(q) = pi * int_0^1 (1 - t^q)^(2/q) dt``: breast volume / (a_u a_w p)."""
    val, _ = integrate.quad(lambda t: (1.0 - t**q) ** (2.0 / q), 0.0, 1.0)
    return float(np.pi * val)


@dataclass(frozen=True)
class PhantomGenerator:
    """Deterministic virtual-patient generator.

    Parameters
    ----------
    seed : int
        Cohort seed; patient ``i`` depends only on ``(seed, i)``.
    voxel_size : float
        Edge of the isotropic voxels, mm.
    """

    seed: int = 0
    voxel_size: float = 1.0

    def __post_init__(self) -> None:
        if not self.voxel_size > 0:
            raise ValueError(f"generator.voxel_size must be > 0 mm, got {self.voxel_size!r}")

    def _rng(self, *keys: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, *keys]))

    def _compression_u(self, index: int) -> float:
        """Quantile of patient ``index``'s compression ratio: a golden-ratio low-discrepancy
        sequence, so that any run of consecutive patients spreads evenly over the whole
        distribution, tails included (it depends only on the seed and the index)."""
        u0 = self._rng(2**31 - 1).random()
        return float((u0 + index * GOLDEN) % 1.0)

    def patient(self, index: int) -> dict:
        """Patient-level facts shared by both breasts."""
        rng = self._rng(index)
        site = SITES[0] if rng.random() < SITES[0].fraction else SITES[1]
        age = _truncated_normal(rng, site.age_mean, site.age_sd, *site.age_range)
        while True:
            volume = float(site.volume_median_cm3 * np.exp(site.volume_sigma * rng.normal()))
            if VOLUME_RANGE_CM3[0] <= volume <= VOLUME_RANGE_CM3[1]:
                break
        category = DENSITY_CATEGORIES[rng.choice(4, p=site.density_probabilities)]
        lo, hi = DENSITY_RANGES[category]
        return {
            "patient": index,
            "site": site.name,
            "age": round(age, 1),
            "volume_cm3": volume,
            "density_category": category,
            "glandular_fraction": float(rng.uniform(lo, hi)),
            "compression_ratio": compression_quantile(site, self._compression_u(index)),
            "shape": rng.uniform(size=8).tolist(),  # shared shape genes, jittered per breast
            "chest_radius": float(rng.uniform(140.0, 220.0)),
            "midline_offset": float(rng.uniform(15.0, 35.0)),
        }

    def shape(self, index: int, laterality: str) -> BreastShape:
        """Parameters of one breast: the patient's, with left/right asymmetry."""
        if laterality not in ("L", "R"):
            raise ValueError(f"laterality must be 'L' or 'R', got {laterality!r}")
        pat = self.patient(index)
        rng = self._rng(index, 0 if laterality == "L" else 1)
        genes = np.clip(np.asarray(pat["shape"]) + rng.normal(0.0, 0.04, 8), 0.0, 1.0)
        volume = float(
            np.clip(pat["volume_cm3"] * np.exp(rng.normal(0.0, 0.07)), *VOLUME_RANGE_CM3)
        )
        # Larger breasts project further and sag more (prone MRI elongates them along AP).
        size = np.clip((np.log(volume) - np.log(100.0)) / np.log(25.0), 0.0, 1.0)
        aspect = 0.75 + 0.25 * genes[0]  # a_w / a_u
        proj_ratio = 0.55 + 0.45 * genes[1] + 0.3 * size  # p / a_u
        q = 1.5 + 1.1 * genes[2]
        ripple = tuple(
            (float(0.035 * rng.uniform()), float(rng.uniform(0.0, 2 * np.pi))) for _ in range(3)
        )
        w_factor = 1.0 + 0.5 * sum(a * a for a, _ in ripple)  # mean of (1 + ripple)^2
        a_u = (volume * 1e3 / (aspect * proj_ratio * profile_area_factor(q) * w_factor)) ** (1 / 3)
        lo, hi = DENSITY_RANGES[pat["density_category"]]
        gland = _reflect(pat["glandular_fraction"] * np.exp(rng.normal(0.0, 0.08)), lo, hi)
        return BreastShape(
            laterality=laterality,
            target_volume_cm3=volume,
            a_u=float(a_u),
            a_w=float(aspect * a_u),
            projection=float(proj_ratio * a_u),
            profile_q=float(q),
            ptosis=float(0.05 + 0.25 * genes[3] + 0.1 * size),
            lateral_turn=float(0.15 * genes[4]),
            ripple=ripple,
            muscle_thickness=float(8.0 + 10.0 * genes[5]),
            chest_radius=pat["chest_radius"],
            midline_offset=pat["midline_offset"],
            glandular_fraction=gland,
            gland_length=float(4.0 + 4.0 * genes[6]),
            gland_bias=float(1.0 + 1.5 * genes[7]),
            subcutaneous_fat=float(rng.uniform(3.0, 8.0)),
            retromammary_fat=float(rng.uniform(2.0, 6.0)),
            compression_ratio=pat["compression_ratio"],
        )

    def breast(self, index: int, laterality: str) -> tuple[LabelVolume, dict]:
        """Labelled volume and metadata of one breast."""
        shape = self.shape(index, laterality)
        pat = self.patient(index)
        rng = self._rng(index, 0 if laterality == "L" else 1, 1)
        volume = label_breast(
            shape, self.voxel_size, rng, source=f"phantom {self.seed}/{index}{laterality}"
        )
        labels = volume.labels
        breast_vox = (labels == Tissue.FAT) | (labels == Tissue.GLAND)
        gland_vox = int((labels == Tissue.GLAND).sum())
        z_idx = np.flatnonzero(breast_vox.any(axis=(0, 1)))
        thickness = float((z_idx[-1] - z_idx[0] + 1) * volume.spacing[2])
        gland_fraction = gland_vox / max(int(breast_vox.sum()), 1)
        meta = {
            "patient": index,
            "laterality": laterality,
            "site": pat["site"],
            "age": pat["age"],
            "breast_volume_cm3": float(breast_vox.sum()) * volume.voxel_volume / 1e3,
            "glandular_fraction": gland_fraction,
            "density_category": density_category(gland_fraction),
            "uncompressed_thickness_mm": thickness,
            "target_compression_ratio": shape.compression_ratio,
            "compressed_thickness_mm": (1.0 - shape.compression_ratio) * thickness,
            # JSON-normal (tuples as lists) so that metadata survives a save/load round trip.
            "phantom": json.loads(
                json.dumps({k: v for k, v in asdict(shape).items() if k != "laterality"})
            ),
        }
        return volume, meta


def label_breast(
    shape: BreastShape, voxel_size: float, rng: np.random.Generator, source: str = "phantom"
) -> LabelVolume:
    """Voxelise one breast (chest wall, muscle, fat, gland) on an axis-aligned RAS+ grid.

    Parameters
    ----------
    shape : BreastShape
        Sampled anatomy.
    voxel_size : float
        Voxel edge, mm.
    rng : numpy.random.Generator
        Source of the glandular random field.

    Returns
    -------
    LabelVolume
        Labels on a grid cropped to the breast and its muscle layer plus a 3-voxel margin.
    """
    s = shape
    side = 1.0 if s.laterality == "R" else -1.0  # RAS+: the right breast lies at +x
    x0 = side * (s.midline_offset + s.a_u)
    z0 = 0.0
    turn, sag = s.lateral_turn * s.a_u, s.ptosis * s.a_w

    def chest(u: NDArray) -> NDArray:  # v of the chest wall at lateral coordinate u
        r = s.midline_offset + s.a_u
        return -((u + r) ** 2 - r**2) / (2.0 * s.chest_radius)

    # Bounding box in local coordinates (u lateral, v anterior, w superior).
    margin = 3 * voxel_size
    u_lo, u_hi = -s.a_u * 1.1 - margin, s.a_u * 1.1 + turn + margin
    w_lo, w_hi = -s.a_w * 1.1 - sag - margin, s.a_w * 1.1 + margin
    v_cw = chest(np.array([u_lo, 0.0, u_hi]))
    v_lo = v_cw.min() - s.muscle_thickness - margin
    v_hi = v_cw.max() + s.projection + margin
    n = np.ceil(np.array([u_hi - u_lo, v_hi - v_lo, w_hi - w_lo]) / voxel_size).astype(int)
    u = (u_lo + (np.arange(n[0]) + 0.5) * voxel_size).astype(np.float32)[:, None, None]
    v = (v_lo + (np.arange(n[1]) + 0.5) * voxel_size).astype(np.float32)[None, :, None]
    w = (w_lo + (np.arange(n[2]) + 0.5) * voxel_size).astype(np.float32)[None, None, :]

    d = v - chest(u)  # depth from the chest wall, (I, J, 1) broadcast
    t = np.clip(d / s.projection, 0.0, 1.0)
    cu, cw = turn * t**2, -sag * t**2
    du, dw = (u - cu) / s.a_u, (w - cw) / s.a_w
    rho = np.sqrt(du**2 + dw**2)
    theta = np.arctan2(dw, du)
    ripple = 1.0 + sum(
        a * np.cos(k * theta + ph) for k, (a, ph) in zip((2, 3, 4), s.ripple, strict=True)
    )
    radius = (1.0 - t**s.profile_q) ** (1.0 / s.profile_q) * ripple  # profile r(d)
    breast = (d >= 0) & (d <= s.projection) & (rho <= radius)
    base = np.sqrt((u / s.a_u) ** 2 + (w / s.a_w) ** 2) <= ripple  # footprint at d = 0
    muscle = (d < 0) & (d >= -s.muscle_thickness) & base

    # Fibroglandular tissue: smooth Gaussian field + retroareolar bias, quantile-thresholded.
    coarse = max(2, round(s.gland_length / (2 * voxel_size)))
    field = rng.standard_normal(np.ceil(n / coarse).astype(int) + 1).astype(np.float32)
    field = ndimage.gaussian_filter(field, s.gland_length / (coarse * voxel_size), mode="wrap")
    field = ndimage.zoom(field, coarse, order=1)[: n[0], : n[1], : n[2]]
    field /= field.std() + 1e-12
    s_norm = rho / np.maximum(radius, 1e-6)  # 0 on the breast axis, 1 at the skin
    bias = s.gland_bias * (1.0 - s_norm**2) * np.exp(-(((t - 0.5) / 0.35) ** 2))
    score = field + bias
    local_r = np.maximum(radius * np.sqrt(s.a_u * s.a_w), 1e-6)  # mean radius at that depth
    eligible = (
        breast
        & ((1.0 - s_norm) * local_r > s.subcutaneous_fat)
        & (d > s.retromammary_fat)
        & (d < s.projection - s.subcutaneous_fat)
    )
    n_gland = round(s.glandular_fraction * breast.sum())
    labels = np.zeros(tuple(n), np.uint8)
    labels[muscle] = Tissue.MUSCLE
    labels[breast] = Tissue.FAT
    candidates = score[eligible]
    if n_gland > 0 and candidates.size:
        k = min(n_gland, candidates.size)
        threshold = np.partition(candidates, candidates.size - k)[candidates.size - k]
        labels[eligible & (score >= threshold)] = Tissue.GLAND

    # Local -> world: x = x0 + side * u, y = v, z = z0 + w; mirror the left breast's x axis so
    # that the voxel axes stay aligned with RAS+ (i increases with x).
    if side < 0:
        labels = labels[::-1]
        i0 = x0 - (u_lo + n[0] * voxel_size) + 0.5 * voxel_size
    else:
        i0 = x0 + u_lo + 0.5 * voxel_size
    affine = np.diag([voxel_size, voxel_size, voxel_size, 1.0])
    affine[:3, 3] = [i0, v_lo + 0.5 * voxel_size, z0 + w_lo + 0.5 * voxel_size]
    return LabelVolume(np.ascontiguousarray(labels), affine, source)
