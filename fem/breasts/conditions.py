"""Per-breast simulation conditions of the cohort v2: stiffness, friction, view, thickness.

The paper's cohort simulates every breast with the same conditions (`conf/simulation/`:
fat 1100, gland 2500, muscle 6000, skin 1000 Pa, friction 0.25, cranio-caudal plates, the
breast's own compression ratio). With a `ConditionSampler` (the ``variation`` setting of the
cohort, `conf/variation/v2.yaml`) each breast gets its own: Young's moduli drawn log-uniformly
per tissue, a friction coefficient drawn uniformly, one simulation per configured view (cc,
mlo) with its own oblique angle and its own compressed thickness (the breast's target
compression ratio times a drawn factor, clipped). The ranges and their sources are in
docs/cohort.md ("Cohort v2").

Every draw is a pure function of ``(seed, breast name)`` (and the view, for what depends on
it), never of the order in which breasts are simulated or of Python's string hashing, so a
resumed or distributed run draws the same conditions::

    sampler = ConditionSampler(young={"fat": (550.0, 3300.0)}, friction=(0.1, 0.5))
    draw = sampler.sample("P0007_L", target_ratio=0.45, view="cc")
    simulation = dataclasses.replace(simulation, **sampler.overrides(simulation, draw))
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fem.engine.boundary import VIEWS
from fem.engine.simulation import SKIN_THICKNESS, TISSUE_NAMES, Simulation

#: The names a Young's modulus range may be given for: the tissues and the skin membrane.
SAMPLED_MATERIALS = (*TISSUE_NAMES, "skin")


def _pair(
    value: object, key: str, rule: str, holds: Callable[[float, float], bool]
) -> tuple[float, float]:
    """``value`` as ``(low, high)`` floats, or a ValueError naming ``variation.<key>``."""
    low = high = math.nan
    if isinstance(value, Sequence) and not isinstance(value, str | bytes) and len(value) == 2:
        try:
            low, high = float(value[0]), float(value[1])
        except (TypeError, ValueError):
            pass
    if not (math.isfinite(low) and math.isfinite(high) and holds(low, high)):
        raise ValueError(f"variation.{key} must be [low, high] with {rule}, got {value!r}")
    return low, high


def _name_key(text: str) -> int:
    """A stable 32-bit key of ``text`` (CRC-32 of its UTF-8 bytes, never ``hash()``)."""
    return zlib.crc32(text.encode("utf-8"))


@dataclass(frozen=True)
class ConditionSampler:
    """Per-breast simulation conditions drawn from ranges: the cohort's ``variation``.

    Parameters
    ----------
    young : mapping of str to (2,) float
        Young's modulus range ``[low, high]`` in Pa per material, drawn log-uniformly:
        ``fat``, ``gland``, ``muscle`` and ``skin`` (the membrane). A material left out keeps
        the simulation's setting; ``low == high`` fixes it.
    friction : (2,) float
        Coulomb friction coefficient range between skin and plates, drawn uniformly; >= 0.
    views : sequence of {"cc", "mlo"}
        The views every breast is simulated in, each once; the first one's trajectories go to
        ``<out_dir>/trajectories``, any other's to ``<out_dir>/trajectories_<view>``.
    angle : (2,) float
        Range of the mlo plates' angle from the cc plates, degrees, drawn uniformly per breast
        and view, within (0, 90). A cc simulation keeps the simulation's ``angle`` (unused).
    compression_ratio_factor : (2,) float
        Range of the factor on the breast's target compression ratio (its metadata's, or
        ``simulation.compression_ratio``), drawn uniformly per breast and view: different
        compressed thicknesses for the same breast and for its views. Dimensionless, > 0.
    compression_ratio_range : (2,) float
        The interval the jittered compression ratio is clipped to, within (0, 1).
    poisson : float
        Poisson's ratio of the sampled materials, in [0, 0.5) (the paper's 0.495).
    skin_membrane : float
        Thickness of the sampled skin membrane, mm (the paper's 2 mm).
    seed : int
        Seed of the draws, >= 0; a breast's conditions depend only on ``(seed, name)`` and,
        for the angle and the compression ratio, on the view.

    Raises
    ------
    ValueError
        A range that is not ``[low, high]`` inside its domain, an unknown material or view,
        a repeated view, or a bad seed; the message names the setting (``variation.<key>``).
    """

    young: Mapping[str, Sequence[float]] = field(default_factory=dict)
    friction: Sequence[float] = (0.25, 0.25)
    views: Sequence[str] = ("cc",)
    angle: Sequence[float] = (45.0, 45.0)
    compression_ratio_factor: Sequence[float] = (1.0, 1.0)
    compression_ratio_range: Sequence[float] = (0.05, 0.775)
    poisson: float = 0.495
    skin_membrane: float = SKIN_THICKNESS
    seed: int = 0

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: the validated, normalised values replace the inputs
        if not isinstance(self.young, Mapping):
            raise ValueError(
                f"variation.young must map materials ({', '.join(SAMPLED_MATERIALS)}) to "
                f"[low, high] in Pa, got {self.young!r}"
            )
        young = {}
        for name, value in self.young.items():
            if name not in SAMPLED_MATERIALS:
                raise ValueError(
                    f"variation.young.{name}: not a material of the simulation "
                    f"({', '.join(SAMPLED_MATERIALS)})"
                )
            young[str(name)] = _pair(
                value, f"young.{name}", "0 < low <= high (Pa)", lambda lo, hi: 0 < lo <= hi
            )
        set_(self, "young", {n: young[n] for n in SAMPLED_MATERIALS if n in young})
        ranges = {  # setting: (rule, holds)
            "friction": ("0 <= low <= high", lambda lo, hi: 0 <= lo <= hi),
            "angle": ("0 < low <= high < 90 (degrees)", lambda lo, hi: 0 < lo <= hi < 90),
            "compression_ratio_factor": ("0 < low <= high", lambda lo, hi: 0 < lo <= hi),
            "compression_ratio_range": ("0 < low <= high < 1", lambda lo, hi: 0 < lo <= hi < 1),
        }
        for key, (rule, holds) in ranges.items():
            set_(self, key, _pair(getattr(self, key), key, rule, holds))
        views = self.views
        if isinstance(views, str) or not isinstance(views, Sequence) or not views:
            raise ValueError(f"variation.views must be a non-empty list of {VIEWS}, got {views!r}")
        views = tuple(views)
        if any(v not in VIEWS for v in views) or len(set(views)) != len(views):
            raise ValueError(
                f"variation.views must be distinct views among {VIEWS}, got {list(views)!r}"
            )
        set_(self, "views", views)
        if not (isinstance(self.poisson, int | float) and 0 <= self.poisson < 0.5):
            raise ValueError(f"variation.poisson must lie in [0, 0.5), got {self.poisson!r}")
        if not (isinstance(self.skin_membrane, int | float) and self.skin_membrane > 0):
            raise ValueError(f"variation.skin_membrane must be > 0 mm, got {self.skin_membrane!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"variation.seed must be an integer >= 0, got {self.seed!r}")

    def _rng(self, name: str, view: str | None = None) -> np.random.Generator:
        keys = [self.seed, _name_key(name)] + ([] if view is None else [_name_key(view)])
        return np.random.default_rng(keys)

    def sample(self, name: str, target_ratio: float, view: str | None = None) -> dict[str, Any]:
        """The conditions of breast ``name`` in ``view``, as `Simulation` arguments.

        Parameters
        ----------
        name : str
            The breast's name (``P0007_L``): with ``seed``, all its draws come from it.
        target_ratio : float
            The breast's own target compression ratio, in (0, 1): jittered by the drawn
            factor and clipped to ``compression_ratio_range``.
        view : {"cc", "mlo"}, optional
            One of ``views``; default the first.

        Returns
        -------
        dict
            ``materials`` (name -> ``{"young": Pa, "poisson": -}``, the skin also with
            ``"membrane": mm``; the same for every view of the breast), ``friction`` (the same
            for every view), ``view``, ``angle`` (degrees; mlo only), ``compression_ratio``
            and ``compression_ratio_factor`` (the drawn factor, dimensionless; not a
            `Simulation` argument: `overrides` leaves it out).

        Raises
        ------
        ValueError
            ``view`` not among ``views``, or ``target_ratio`` outside (0, 1).
        """
        view = self.views[0] if view is None else view
        if view not in self.views:
            raise ValueError(f"view {view!r} is not among variation.views {list(self.views)}")
        if not 0 < target_ratio < 1:
            raise ValueError(
                f"{name}: target compression ratio must lie in (0, 1), got {target_ratio!r}"
            )
        rng = self._rng(name)  # the breast's tissue and skin: the same in every view
        materials: dict[str, dict[str, float]] = {}
        for material in SAMPLED_MATERIALS:  # in a fixed order, one draw each, sampled or not:
            # a material added to or left out of the config moves no other draw
            low, high = self.young.get(material, (1.0, 1.0))
            e = float(np.exp(rng.uniform(np.log(low), np.log(high))))
            if material in self.young:
                materials[material] = {"young": e, "poisson": float(self.poisson)}
                if material == "skin":
                    materials[material]["membrane"] = float(self.skin_membrane)
        friction = float(rng.uniform(*self.friction))
        per_view = self._rng(name, view)  # the plates: per view
        angle = float(per_view.uniform(*self.angle))
        factor = float(per_view.uniform(*self.compression_ratio_factor))
        ratio = float(np.clip(target_ratio * factor, *self.compression_ratio_range))
        out: dict[str, Any] = {"materials": materials, "friction": friction, "view": view}
        if view == "mlo":
            out["angle"] = angle
        out.update(compression_ratio=ratio, compression_ratio_factor=factor)
        return out

    def check(self, simulation: Simulation) -> None:
        """Refuse a simulation the draws cannot be applied to.

        Raises
        ------
        ValueError
            ``simulation.plates`` is set (the draws set the view and the compression ratio),
            or a sampled skin replaces a solid skin element set.
        """
        if simulation.plates is not None:
            raise ValueError(
                "variation: simulation.plates must be null (the variation draws the view and "
                "the compression ratio of each breast)"
            )
        skin = simulation.materials.get("skin")
        if "skin" in self.young and skin is not None and skin.elements is not None:
            raise ValueError(
                "variation.young.skin: simulation.materials.skin is a solid element set, not "
                "the membrane the variation samples"
            )

    @staticmethod
    def overrides(simulation: Simulation, draw: Mapping[str, Any]) -> dict[str, Any]:
        """The `Simulation` arguments of a `sample` draw: its materials laid over the
        simulation's (those not sampled, element sets included, stay), ready for
        ``dataclasses.replace(simulation, **overrides)``."""
        out = {k: v for k, v in draw.items() if k != "compression_ratio_factor"}
        out["materials"] = {**simulation.materials, **draw["materials"]}
        return out
