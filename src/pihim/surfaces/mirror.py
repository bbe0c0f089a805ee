"""Heliostat mirror reflection models (Mueller matrices in the s/p basis).

Three models share one interface:

``mueller(cos_i) -> (..., 4, 4)``
    Reflection Mueller matrix for the cosine ``cos_i`` of the angle of
    incidence at the front surface, vectorised over ``cos_i``, in the basis
    of :mod:`pihim.polarimetry.reflection`: **s (perpendicular to the plane of
    incidence) is the x axis** of both the incident and the reflected frame,
    ``p = d x s`` completes each frame, and a perfect conductor has
    ``r_s = -1``, ``r_p = +1`` (Mueller ``diag(1, 1, -1, -1)``).
``reflect(s, d, e, normal)``
    Convenience wrapper of :func:`pihim.polarimetry.reflection.reflect_stokes`
    with the model's Mueller matrix.

Models
------
:class:`SecondSurfaceMirror` (default)
    Silvered glass as used on heliostats: reflection at the air | glass
    front surface plus the light refracted into the glass, reflected by the
    glass | silver interface and refracted back out, with the geometric series
    of further internal bounces and optional bulk absorption in the glass.
    The paths are added incoherently (Mueller matrices summed) because the
    glass (millimetres) is far thicker than the coherence length of sunlight
    and skylight (about a micrometre broadband, some tens of micrometres
    behind a 10 nm filter).
:class:`IdealMirror`
    A perfect conductor, optionally scaled by a reflectance.
:class:`FresnelMirror`
    The paper's plain two-medium Fresnel reflection (eqs. 4-7): ambient |
    medium with a complex index.

Optical constants are for one fixed design wavelength,
:data:`DESIGN_WAVELENGTH_NM` = 550 nm (the middle of the visible band of the
polarization camera); they are parameters of the models, so other
wavelengths only need other indices.

Sign conventions: complex indices are ``N = n + i k`` with ``k >= 0`` (time
dependence ``exp(-i omega t)``, Born & Wolf), as in
:mod:`pihim.surfaces.fresnel`. The circular entries ``M23 = -M32 =
Im(r_s r_p*)`` follow the paper's eq. (5); with this time convention they
imply ``S3 > 0`` for a field turning from s toward p (counter-clockwise when
looking into the beam). Mitsuba 3 uses the opposite time convention and the
opposite ``S3`` handedness (its ``M23``, ``M32`` have the other sign; see
``tests/surfaces/test_fresnel_oracle.py``). Only the circular entries depend
on this; DoLP and AoP do not.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", eqs. (4)-(7).
.. [2] M. Born, E. Wolf, *Principles of Optics*, 7th ed., Cambridge
   University Press, 1999, sec. 1.5 (Fresnel formulae) and 14.2 (metals).
.. [3] P. B. Johnson, R. W. Christy, "Optical constants of the noble
   metals", Phys. Rev. B 6, 4370-4379 (1972), doi:10.1103/PhysRevB.6.4370;
   silver, tabulated at 548.6 nm (2.26 eV): n = 0.06, k = 3.586 (values as
   given by refractiveindex.info, ``data-nk/main/Ag/Johnson.yml``).
.. [4] M. Rubin, "Optical properties of soda lime silica glasses", Solar
   Energy Materials 12, 275-288 (1985), doi:10.1016/0165-1633(85)90052-8;
   low-iron glass, Cauchy fit ``n = 1.5130 - 0.003169 l^2 + 0.003962 l^-2``
   (``l`` in um) and tabulated extinction ``k(0.55 um) = 4.632e-8`` (values
   as given by refractiveindex.info,
   ``data-nk/glass/misc/soda-lime/Rubin-lowiron.yml``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.reflection import reflect_stokes
from pihim.surfaces.fresnel import (
    _as_cos,
    fresnel_amplitudes,
    fresnel_reflection_mueller,
    fresnel_transmission_mueller,
)

#: Design wavelength (nm) of the default optical constants.
DESIGN_WAVELENGTH_NM = 550.0

#: Low-iron soda-lime glass at 550 nm, Rubin (1985) Cauchy fit: 1.52514.
N_GLASS_LOW_IRON_550 = 1.5251

#: Silver, Johnson & Christy (1972), tabulated point nearest 550 nm
#: (548.6 nm, 2.26 eV). Interpolating to 550 nm (k = 3.597) changes the
#: mirror reflectance by less than 1e-3.
N_SILVER_JC_550 = complex(0.06, 3.586)

#: Bulk (intensity) absorption coefficient of low-iron glass at 550 nm,
#: ``4 pi k / lambda`` with Rubin's ``k = 4.632e-8``: 1.058e-3 per mm, i.e. an
#: internal transmittance of 0.9958 per normal pass through 4 mm. Solar-
#: weighted transmittances are lower because of the Fe2+ absorption band near
#: 1 um, outside the visible band of the polarization camera; no solar-weighted
#: figure is used here.
GLASS_ABSORPTION_LOW_IRON_550_PER_MM = 4.0 * math.pi * 4.632e-8 / (DESIGN_WAVELENGTH_NM * 1e-6)

#: Default glass thickness (mm) of a heliostat mirror facet.
GLASS_THICKNESS_MM = 4.0

MirrorName = Literal["second-surface", "ideal", "fresnel"]


def _real_param(name: str, value: Any, *, minimum: float, strict: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise PihimInputError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < minimum or (strict and v == minimum):
        op = ">" if strict else ">="
        raise PihimInputError(f"{name} must be finite and {op} {minimum:g}, got {value!r}")
    return v


def _complex_param(name: str, value: Any) -> complex:
    try:
        v = complex(value.replace(" ", "")) if isinstance(value, str) else complex(value)
    except (TypeError, ValueError):
        raise PihimInputError(f"{name} must be a (complex) refractive index n + ik, got {value!r}") from None
    if not (math.isfinite(v.real) and math.isfinite(v.imag)) or v.real < 0.0 or v.imag < 0.0 or v == 0:
        raise PihimInputError(f"{name} must be n + ik with n >= 0, k >= 0 (not both 0), got {value!r}")
    return v


def _mueller_from_sp(r_s: NDArray, r_p: NDArray, x: NDArray) -> NDArray[np.float64]:
    """Mueller matrix ``(..., 4, 4)`` from s and p intensity factors and the cross term ``x``.

    For a single interface ``r_s = |a_s|^2``, ``r_p = |a_p|^2``, ``x = a_s a_p*``
    (the layout of :func:`pihim.polarimetry.reflection.mueller_from_amplitudes`).
    Every Mueller matrix of this block form is fixed by ``(r_s, r_p, x)``;
    products of such matrices multiply the three factors and sums add them.
    """
    r_s, r_p, x = np.broadcast_arrays(np.asarray(r_s, float), np.asarray(r_p, float), np.asarray(x, complex))
    m = np.zeros((*r_s.shape, 4, 4))
    m[..., 0, 0] = m[..., 1, 1] = 0.5 * (r_s + r_p)
    m[..., 0, 1] = m[..., 1, 0] = 0.5 * (r_s - r_p)
    m[..., 2, 2] = m[..., 3, 3] = x.real
    m[..., 2, 3] = x.imag
    m[..., 3, 2] = -x.imag
    return m


def _sp(a_s: NDArray, a_p: NDArray, scale: ArrayLike = 1.0) -> tuple[NDArray, NDArray, NDArray]:
    """``(scale |a_s|^2, scale |a_p|^2, scale a_s a_p*)`` of one interface."""
    return scale * np.abs(a_s) ** 2, scale * np.abs(a_p) ** 2, scale * a_s * np.conj(a_p)


def _sp_of(m: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Inverse of :func:`_mueller_from_sp`: ``(M00 + M01, M00 - M01, M22 + i M23)``."""
    return m[..., 0, 0] + m[..., 0, 1], m[..., 0, 0] - m[..., 0, 1], m[..., 2, 2] + 1j * m[..., 2, 3]


class MirrorModel(ABC):
    """Interface shared by the mirror models."""

    @abstractmethod
    def mueller(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        """Reflection Mueller matrix ``(..., 4, 4)``, s as the x axis, for ``cos_i`` in [0, 1]."""

    def unpolarized_reflectance(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        """Reflectance for unpolarized light, ``M00`` (dimensionless)."""
        return self.mueller(cos_i)[..., 0, 0]

    def reflect(
        self, s: ArrayLike, d: ArrayLike, e: ArrayLike, normal: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Reflect Stokes ``s`` (..., 4) travelling along ``d`` with reference ``e`` off the mirror.

        See :func:`pihim.polarimetry.reflection.reflect_stokes`; returns
        ``(s_out, d_out, s_axis)`` with ``s_out`` in the frame
        (``d_out``, ``s_axis``).
        """
        return reflect_stokes(s, d, e, normal, self.mueller)


@dataclass(frozen=True)
class IdealMirror(MirrorModel):
    """Perfect conductor: ``r_s = -1``, ``r_p = +1``, Mueller ``reflectance * diag(1, 1, -1, -1)``.

    Preserves DoLP and DoP exactly, mirrors the AoP about the plane of
    incidence (the AoP measured from s changes sign) and flips the
    handedness of circular light.

    Parameters
    ----------
    reflectance : float
        Scalar, polarization-independent reflectance in [0, 1].
    """

    reflectance: float = 1.0

    def __post_init__(self) -> None:
        r = _real_param("reflectance", self.reflectance, minimum=0.0)
        if r > 1.0:
            raise PihimInputError(f"reflectance must be in [0, 1], got {self.reflectance!r}")
        object.__setattr__(self, "reflectance", r)

    def mueller(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        c = _as_cos(cos_i)
        m = np.zeros((*c.shape, 4, 4))
        diag = self.reflectance * np.array([1.0, 1.0, -1.0, -1.0])
        m[..., [0, 1, 2, 3], [0, 1, 2, 3]] = np.where(np.isnan(c)[..., None], np.nan, diag)
        return m


@dataclass(frozen=True)
class FresnelMirror(MirrorModel):
    """The paper's two-medium Fresnel reflection (eqs. 4-7): ambient | medium of index ``n``.

    Parameters
    ----------
    n : complex
        Index ``n + ik`` of the reflecting medium at the design wavelength.
        Default: silver, Johnson & Christy (1972) at 548.6 nm (a bare,
        first-surface silver mirror). The paper does not state the index it
        used for the mirror; ``n = 1.5251`` gives a bare glass surface.
    n_ambient : float
        Real index of the medium the light comes from (air, 1.0).
    """

    n: complex = N_SILVER_JC_550
    n_ambient: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "n", _complex_param("n", self.n))
        object.__setattr__(self, "n_ambient", _real_param("n_ambient", self.n_ambient, minimum=0.0, strict=True))

    def mueller(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        return fresnel_reflection_mueller(_as_cos(cos_i), self.n_ambient, self.n)


@dataclass(frozen=True)
class SecondSurfaceMirror(MirrorModel):
    """Silvered glass (second-surface) heliostat mirror, paths added incoherently.

    Light paths, all in the same plane of incidence (so the s axis is common
    and the Mueller matrices of the block form of
    :func:`pihim.polarimetry.reflection.mueller_from_amplitudes` simply
    multiply)::

        M = R01 + T10 . sum_k (A . R10)^k . A . T01,   A = tau^2 R12

    ``R01``: air (n = 1) | glass reflection at the front; ``T01``, ``T10``: refraction
    into and out of the glass (power transmission,
    :func:`pihim.surfaces.fresnel.fresnel_transmission_mueller`); ``R12``:
    glass | silver reflection at the refraction angle ``theta_g``; ``R10``:
    reflection of the up-going light at the inside of the front surface,
    which sends it back to the silver; ``tau = exp(-alpha t / cos theta_g)``:
    bulk transmittance of one pass. The series sums to
    ``(I - A R10)^-1`` exactly (evaluated in closed form on the
    ``(r_s, r_p, r_s r_p*)`` factors, see :func:`_mueller_from_sp`).

    The internal bounces are **included by default**: ``R10 ~ 0.043`` at
    normal incidence, so they return about 4 % of the light that reaches the
    silver (normal-incidence reflectance 0.968 with, 0.929 without). Set
    ``multiple_reflections=False`` for the single-pass model.

    Neglected: interference in the glass (incoherent sum), transmission
    through the silver (opaque: its thickness, ~100 nm, is many skin depths
    of ~12 nm), the copper and paint behind it, soiling, and scattering.

    Parameters
    ----------
    n_glass : float
        Real index of the glass (default low-iron soda-lime, 1.5251 at 550 nm,
        Rubin 1985).
    n_silver : complex
        Index ``n + ik`` of the silver (default Johnson & Christy 1972 at
        548.6 nm: 0.06 + 3.586i).
    thickness_mm : float
        Glass thickness in mm (default 4).
    absorption_per_mm : float
        Bulk intensity absorption coefficient of the glass in 1/mm (default
        low-iron glass at 550 nm, 1.058e-3/mm, Rubin 1985: 0.9958 internal
        transmittance per normal pass through 4 mm). 0 disables absorption.
    multiple_reflections : bool
        Include the geometric series of glass-internal bounces.
    """

    n_glass: float = N_GLASS_LOW_IRON_550
    n_silver: complex = N_SILVER_JC_550
    thickness_mm: float = GLASS_THICKNESS_MM
    absorption_per_mm: float = GLASS_ABSORPTION_LOW_IRON_550_PER_MM
    multiple_reflections: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_glass", _real_param("n_glass", self.n_glass, minimum=1.0))
        object.__setattr__(self, "n_silver", _complex_param("n_silver", self.n_silver))
        object.__setattr__(self, "thickness_mm", _real_param("thickness_mm", self.thickness_mm, minimum=0.0))
        object.__setattr__(
            self, "absorption_per_mm", _real_param("absorption_per_mm", self.absorption_per_mm, minimum=0.0)
        )
        mr = self.multiple_reflections
        if isinstance(mr, str):
            if mr.strip().lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise PihimInputError(f"multiple_reflections must be a boolean, got {mr!r}")
            mr = mr.strip().lower() in ("true", "1", "yes")
        elif not isinstance(mr, (bool, np.bool_)):
            raise PihimInputError(f"multiple_reflections must be a boolean, got {mr!r}")
        object.__setattr__(self, "multiple_reflections", bool(mr))

    def glass_cos(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        """Cosine of the refraction angle inside the glass (Snell's law, real indices)."""
        c = _as_cos(cos_i)
        return np.sqrt(1.0 - (1.0 - c**2) / self.n_glass**2)

    def mueller(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        c = _as_cos(cos_i)
        ng, nag = self.n_glass, self.n_silver
        with np.errstate(invalid="ignore", divide="ignore"):  # NaN cos_i propagate silently
            cg = self.glass_cos(c)
            tau2 = np.exp(-2.0 * self.absorption_per_mm * self.thickness_mm / cg)

            # one factor triple (s, p, cross) per interface; products multiply, sums add
            front = _sp(*fresnel_amplitudes(c, 1.0, ng))  # R01
            into = _sp_of(fresnel_transmission_mueller(c, 1.0, ng))  # T01
            out = _sp_of(fresnel_transmission_mueller(cg, ng, 1.0))  # T10
            silver = _sp(*fresnel_amplitudes(cg, ng, nag), tau2)  # A = tau^2 R12
            inner_front = _sp(*fresnel_amplitudes(cg, ng, 1.0))  # R10

            parts = []
            for k in range(3):
                path = into[k] * silver[k] * out[k]
                if self.multiple_reflections:
                    path = path / (1.0 - silver[k] * inner_front[k])
                parts.append(front[k] + path)
        return _mueller_from_sp(*parts)


_MODELS: dict[str, type[MirrorModel]] = {
    "second-surface": SecondSurfaceMirror,
    "ideal": IdealMirror,
    "fresnel": FresnelMirror,
}


def mirror_model(name: MirrorName = "second-surface", **params: Any) -> MirrorModel:
    """Build a mirror model by name (for the CLI).

    Parameters
    ----------
    name : {"second-surface", "ideal", "fresnel"}
        :class:`SecondSurfaceMirror` (default), :class:`IdealMirror` or
        :class:`FresnelMirror`.
    **params
        Constructor parameters of that model; strings are accepted for numbers
        (``n="0.06+3.586j"``).

    Raises
    ------
    pihim.errors.PihimInputError
        Unknown model name, unknown parameter or invalid value.
    """
    key = str(name).strip().lower()
    if key not in _MODELS:
        raise PihimInputError(f"unknown mirror model {name!r}; choose one of {', '.join(_MODELS)}")
    cls = _MODELS[key]
    allowed = [f.name for f in fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise PihimInputError(f"mirror model {key!r} has no parameter {unknown[0]!r}; accepted: {', '.join(allowed)}")
    return cls(**params)
