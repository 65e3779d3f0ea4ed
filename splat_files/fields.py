"""3D Gaussian splats as the files of other tools hold them (``SplatFields``), checked like
every file we read: a value no renderer can draw is refused in one line, naming the splat.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from palette_core.errors import InputError

#: The degree-0 spherical harmonic, Y_0^0 = 1 / (2 sqrt(pi)): colour = SH_C0 sh0 + 0.5.
SH_C0 = 0.28209479177387814
#: Coefficients of degrees 1 and up (B - 1) by spherical-harmonic degree, and back.
REST_COEFFICIENTS = {0: 0, 1: 3, 2: 8, 3: 15}
DEGREES = {rest: degree for degree, rest in REST_COEFFICIENTS.items()}
#: Largest |logit opacity| and |log scale| accepted: beyond them float32's sigmoid is 0 or 1
#: and exp overflows or vanishes, so such a value is a broken or hostile file, not a scene.
MAX_LOGIT, MAX_LOG_SCALE = 100.0, 80.0
#: Largest |coefficient| of a colour's spherical harmonics (a colour of +-1000 in [0, 1]).
MAX_COEFFICIENT = 1e4
#: The most a deflate stream expands (RFC 1951's longest match, 258 bytes from 2 bits): the
#: bound on what a compressed container may declare.
MAX_RATIO = 1032


@dataclass
class SplatFields:
    """Splats in the 3D Gaussian splatting PLY's conventions, whatever file they came from
    (each reader converts: SPZ's axes, ``.splat``'s linear scales and bytes).

    Attributes
    ----------
    means : (S, 3) float32
        Positions, in the PLY's frame (x right, y down, z forward: RDF).
    sh0 : (S, 3) float32
        Degree-0 spherical-harmonic coefficients: colour = ``SH_C0 * sh0 + 0.5``.
    shN : (S, B - 1, 3) float32
        Coefficients of degrees 1 and up (B - 1 of 0, 3, 8 or 15), in the basis order of
        3D Gaussian splatting.
    opacities : (S,) float32
        Logits of the peak opacity.
    scales : (S, 3) float32
        Logs of the standard deviations.
    quats : (S, 4) float32
        Rotations (w, x, y, z), of any non-zero length.
    comments : list of str
        A PLY header's comments, written again into a PLY.
    extras : dict of str to (S,) array
        A PLY vertex's other properties (normals, labels), written again into a PLY.
    """

    means: np.ndarray
    sh0: np.ndarray
    shN: np.ndarray
    opacities: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    comments: list[str] = field(default_factory=list)
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.means)

    @property
    def degree(self) -> int:
        """The spherical-harmonic degree of the colours (0 to 3)."""
        return DEGREES[self.shN.shape[1]]

    def colours(self) -> np.ndarray:
        """(S, 3) float64 the degree-0 colours, ``SH_C0 * sh0 + 0.5`` (not clipped)."""
        return SH_C0 * self.sh0.astype(np.float64) + 0.5

    def with_colour(self, sh0: np.ndarray, shN: np.ndarray) -> SplatFields:
        """The same splats with other colour coefficients (float32)."""
        return replace(self, sh0=np.asarray(sh0, np.float32), shN=np.asarray(shN, np.float32))

    def checked(self, name: str) -> SplatFields:
        """``self``, after checking shapes and values; ``name`` says where they came from.

        Raises
        ------
        InputError
            On a shape that does not match, NaN or infinity, a quaternion of length zero,
            or a logit opacity, log scale or coefficient beyond ``MAX_LOGIT``,
            ``MAX_LOG_SCALE`` or ``MAX_COEFFICIENT``, naming the attribute and the splat.
        """
        s = len(self.means)
        shapes = {"means": (s, 3), "sh0": (s, 3), "opacities": (s,), "scales": (s, 3),
                  "quats": (s, 4)}
        for key, shape in shapes.items():
            if getattr(self, key).shape != shape:
                raise InputError(f"{name}: the splats' {key} have shape "
                                 f"{getattr(self, key).shape}, not {shape}")
        if self.shN.ndim != 3 or self.shN.shape[0] != s or self.shN.shape[1:] not in {
                (b, 3) for b in DEGREES}:
            raise InputError(f"{name}: the splats' spherical harmonics have shape "
                             f"{self.shN.shape}, not (S, 0, 3 or 8 or 15, 3)")
        if s == 0:
            raise InputError(f"{name} holds no splats")
        finite = float(np.finfo(np.float32).max)
        limits = {"means": finite, "sh0": MAX_COEFFICIENT, "shN": MAX_COEFFICIENT,
                  "opacities": MAX_LOGIT, "scales": MAX_LOG_SCALE, "quats": finite}
        for key, limit in limits.items():
            value = getattr(self, key).reshape(s, -1)
            bad = ~(np.abs(value) <= limit).all(1) if value.size else np.zeros(s, bool)
            if bad.any():
                i = int(np.argmax(bad))
                what = "NaN or infinite" if not np.isfinite(value[i]).all() else \
                    f"beyond {limit:g} in magnitude"
                raise InputError(f"{name}: splat {i}'s {key} are {what} "
                                 f"({value[i][:4].tolist()})")
        length = np.linalg.norm(self.quats.astype(np.float64), axis=1)
        if (length < 1e-12).any():
            raise InputError(f"{name}: splat {int(np.argmax(length < 1e-12))}'s rotation is a "
                             "quaternion of length zero")
        return self


def as_fields(means, sh0, shN, opacities, scales, quats, **kept) -> SplatFields:  # noqa: N803
    """``SplatFields`` of array-likes, as contiguous float32 (``kept``: comments, extras)."""
    arrays = [np.ascontiguousarray(a, np.float32)
              for a in (means, sh0, shN, opacities, scales, quats)]
    return SplatFields(*arrays, **kept)


def unit_quaternions(quats: np.ndarray) -> np.ndarray:
    """(S, 4) float32 ``quats`` of unit length."""
    return (quats / np.linalg.norm(quats, axis=1, keepdims=True)).astype(np.float32)


def gsply_module(what: str):
    """PyPI's ``gsply``, or InputError saying that ``what`` needs it."""
    try:
        import gsply
    except ImportError:
        raise InputError(f"{what} needs gsply: pip install 'palette-nerf-toolkit[splats]'") \
            from None
    return gsply


def from_gsdata(data, **kept) -> SplatFields:
    """``SplatFields`` of a ``gsply.GSData`` in the PLY's conventions (``kept``: comments)."""
    s = len(data.means)
    shN = np.zeros((s, 0, 3)) if data.shN is None else np.asarray(data.shN)  # noqa: N806
    return as_fields(data.means, data.sh0, shN.reshape(s, -1, 3), data.opacities, data.scales,
                     data.quats, **kept)
