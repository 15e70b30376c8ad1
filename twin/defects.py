"""As-built gears: the nominal (CAD) spec plus known defects, for twins whose answer is known.

A recording of a defective twin states the nominal :class:`GearSpec` as its CAD (``gear`` in
``recording.json``) and renders the as-built gear, nominal + :class:`GearDefects`; the defects
and the quantities an inspector would read from them go to ``recording.json``'s ``truth``.

Defects, all in the gear frame (axis z, tooth 0 centred on +x, tooth k at ``k * 2 pi / z``):

- size / profile: an as-built module or pressure angle (a base-circle error: profile slope),
  and flank modifications along the roll length (slope, crowning), every flank alike;
- per-tooth pitch errors: tooth k turned about the gear axis by ``u_k / r_pitch``;
- eccentric mounting: the gear's axis ``e`` from the turntable axis, so the gear's centre
  circles the turntable axis as it turns;
- chipped teeth: a tip corner cut off by a plane (``size`` along the flank and along the tip
  land), over a z range of the face;
- worn flanks: material removed along the flank normal, ``depth * sin(pi xi)``.

``xi`` is the roll length fraction along the involute: 0 where it starts (base or root
circle), 1 at the tip. Flanks are named as in ISO 21771 seen from the +z face: ``right`` is
the tooth's -theta (clockwise) side, ``left`` its +theta side.

Units: µm for deviations and mm for sizes at this edge (the names say which), mm inside.
"""

from __future__ import annotations

import json
import math
from functools import partial
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, NonNegativeInt, ValidationError

from gearscan.core.gear import GearSpec, bore_loop, extrude

Side = Literal["left", "right"]
SIDE_SIGN: dict[str, int] = {"right": -1, "left": 1}
MIN_SLAB_MM = 0.1  # thinnest z slab between chip ends: thinner ones give sliver walls all round


class DefectError(ValueError):
    """Defects that do not fit the gear, or a defect option that cannot be parsed."""


class Chip(BaseModel):
    """A broken tip corner: the piece of ``tooth`` beyond the plane through the flank point
    ``size_mm`` below the tip circle and the tip-land point ``size_mm`` from the corner."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    tooth: NonNegativeInt
    side: Side = "left"
    size_mm: float = Field(0.3, gt=0, le=5, description="legs of the cut along flank and tip land, mm")
    z_mm: tuple[float, float] | None = Field(None, description="(z_min, z_max) of the chip, mm; None: the whole face width")

    def z_range(self, face_width: float) -> tuple[float, float]:
        return self.z_mm if self.z_mm is not None else (-face_width / 2, face_width / 2)


class Wear(BaseModel):
    """Material worn off one flank along its normal: ``depth_um * sin(pi xi)``, deepest mid-flank."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    tooth: NonNegativeInt
    side: Side = "left"
    depth_um: float = Field(gt=0, le=500)


class GearDefects(BaseModel):
    """How an as-built gear departs from its nominal spec (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    module: float | None = Field(None, gt=0.05, le=50, description="as-built module, mm (None: nominal)")
    pressure_angle_deg: float | None = Field(None, ge=10, le=35, description="as-built pressure angle, deg (None: nominal)")
    profile_slope_um: float = Field(0.0, ge=-200, le=200, description="flank normal offset growing linearly to this at the tip")
    profile_crown_um: float = Field(0.0, ge=-200, le=200, description="flank normal offset 4 c xi (1 - xi): c mid-flank, 0 at the ends")
    pitch_errors_um: dict[NonNegativeInt, Annotated[float, Field(ge=-500, le=500)]] = Field(
        default_factory=dict, description="tooth -> turn of that tooth along the pitch circle, µm (+: +theta)"
    )
    eccentricity_um: float = Field(0.0, ge=0, le=5000, description="gear axis to turntable axis, µm")
    eccentricity_deg: float = Field(0.0, ge=-360, le=360, description="direction of the gear centre in the gear frame, deg")
    chips: tuple[Chip, ...] = ()
    wear: tuple[Wear, ...] = ()

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def from_meta(cls, meta: dict) -> GearDefects | None:
        """The defects a twin ``recording.json`` states in ``truth.defects`` (None if none)."""
        data = (meta.get("truth") or {}).get("defects")
        return cls(**data) if data else None

    @classmethod
    def from_options(
        cls,
        file: Path | None = None,
        *,
        eccentricity_um: float | None = None,
        pitch_errors: list[str] | None = None,
        chips: list[str] | None = None,
        wear: list[str] | None = None,
        module: float | None = None,
    ) -> GearDefects | None:
        """Defects from a JSON ``file`` and CLI options on top of it; None when nothing is given.

        ``pitch_errors``: ``TOOTH:UM``; ``chips``: ``TOOTH:MM[:SIDE[:ZMIN:ZMAX]]``; ``wear``:
        ``TOOTH:UM[:SIDE]``. Options add to (chips, wear, pitch errors) or replace the file's.
        """
        data: dict = {}
        if file is not None:
            try:
                data = json.loads(Path(file).read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise DefectError(f"--defects {file}: {exc}") from exc
            if not isinstance(data, dict):
                raise DefectError(f"--defects {file}: expected a JSON object of GearDefects fields")
        if eccentricity_um is not None:
            data["eccentricity_um"] = eccentricity_um
        if module is not None:
            data["module"] = module
        for text in pitch_errors or []:
            tooth, um = _fields("--pitch-error", text, "TOOTH:UM, e.g. 3:30", 2, 2)
            data.setdefault("pitch_errors_um", {})[tooth] = um
        for text in chips or []:
            f = _fields("--chip", text, "TOOTH:MM[:SIDE[:ZMIN:ZMAX]], e.g. 7:0.3 or 7:0.3:right:-2:2", 2, 5)
            if len(f) == 4:
                raise DefectError(f"--chip {text!r}: give both ZMIN and ZMAX")
            chip = {"tooth": f[0], "size_mm": f[1], **({"side": f[2]} if len(f) > 2 else {})}
            data["chips"] = [*data.get("chips", []), {**chip, **({"z_mm": f[3:]} if len(f) == 5 else {})}]
        for text in wear or []:
            f = _fields("--wear", text, "TOOTH:UM[:SIDE], e.g. 4:20:right", 2, 3)
            data["wear"] = [*data.get("wear", []), {"tooth": f[0], "depth_um": f[1], **({"side": f[2]} if len(f) > 2 else {})}]
        if not data:
            return None
        try:
            return cls(**data)
        except ValidationError as exc:
            raise DefectError("invalid defects: " + _errors(exc)) from exc

    # --- as-built geometry ---------------------------------------------------------------
    @property
    def empty(self) -> bool:
        """True when the as-built gear is its nominal spec."""
        return self == GearDefects()

    def as_built(self, nominal: GearSpec) -> GearSpec:
        """The nominal spec with the as-built module and pressure angle."""
        update = {k: v for k, v in (("module", self.module), ("pressure_angle_deg", self.pressure_angle_deg)) if v is not None}
        try:
            return GearSpec(**{**nominal.model_dump(), **update})
        except ValidationError as exc:
            raise DefectError("the as-built gear is not a gear: " + _errors(exc)) from exc

    @property
    def center(self) -> np.ndarray:
        """The gear axis' position in the turntable frame at encoder angle 0, mm ``(x, y)``."""
        a = math.radians(self.eccentricity_deg)
        return 1e-3 * self.eccentricity_um * np.array([math.cos(a), math.sin(a)])

    def tooth_shift(self, spec: GearSpec) -> np.ndarray:
        """Each tooth's turn about the gear axis, rad ``(z,)``."""
        u = np.zeros(spec.teeth)
        for k, um in self.pitch_errors_um.items():
            u[k] = 1e-3 * um
        return u / spec.pitch_radius

    def roll_fraction(self, spec: GearSpec, radius: np.ndarray | float) -> np.ndarray:
        """``xi``: roll length from the involute's start (0) to the tip circle (1)."""
        rb = spec.base_radius
        length = lambda r: np.sqrt(np.maximum(np.square(r) - rb**2, 0.0))  # noqa: E731
        l0, la = length(max(rb, spec.root_radius)), length(spec.tip_radius)
        return np.clip((length(np.asarray(radius, dtype=float)) - l0) / (la - l0), 0.0, 1.0)

    def flank_offset(self, spec: GearSpec, tooth: int, side: int, radius: np.ndarray | float) -> np.ndarray:
        """Normal offset of a flank (side -1 right, +1 left) at ``radius``, mm (+: material added).

        Profile slope, crowning and wear; pitch errors, size and eccentricity are not in it.
        """
        xi = self.roll_fraction(spec, radius)
        d = 1e-3 * (self.profile_slope_um * xi + self.profile_crown_um * 4 * xi * (1 - xi))
        for w in self.wear:
            if w.tooth == tooth and SIDE_SIGN[w.side] == side:
                d = d - 1e-3 * w.depth_um * np.sin(np.pi * xi)
        return d

    @property
    def _has_flank_offset(self) -> bool:
        return bool(self.profile_slope_um or self.profile_crown_um or self.wear)

    def check(self, nominal: GearSpec) -> GearSpec:
        """Raise :class:`DefectError` naming the field that does not fit ``nominal``; return the as-built spec."""
        spec = self.as_built(nominal)
        z, m, half = spec.teeth, spec.module, spec.face_width / 2
        for k, um in self.pitch_errors_um.items():
            if k >= z:
                raise DefectError(f"pitch_errors_um: tooth {k} does not exist (0 to {z - 1})")
            if abs(um) > 100 * m:
                raise DefectError(f"pitch_errors_um[{k}]={um} must be within ±{100 * m:g} µm (0.1 module)")
        for name, items in (("chips", self.chips), ("wear", self.wear)):
            seen = set()
            for i, d in enumerate(items):
                if d.tooth >= z:
                    raise DefectError(f"{name}[{i}].tooth={d.tooth} does not exist (0 to {z - 1})")
                if (d.tooth, d.side) in seen:
                    raise DefectError(f"{name}[{i}]: tooth {d.tooth} {d.side} flank is listed twice")
                seen.add((d.tooth, d.side))
        # the tip land left after profile slope and chips
        ra, rb = spec.tip_radius, spec.base_radius
        land = 2 * ra * (spec.tip_half_angle + 1e-3 * self.profile_slope_um / rb)
        if land < 0.1 * m:
            raise DefectError(f"profile_slope_um={self.profile_slope_um} leaves a tip land of {land:.3f} mm (needs >= {0.1 * m:.3f})")
        flank_len = ra - max(rb, spec.root_radius)
        for i, c in enumerate(self.chips):
            other = sum(o.size_mm for o in self.chips if o.tooth == c.tooth and o is not c)
            limit = min(land - other - 0.05 * m, 0.9 * flank_len)
            if c.size_mm > limit:
                raise DefectError(f"chips[{i}].size_mm={c.size_mm} must be below {limit:.3f} mm (tip land and flank of tooth {c.tooth})")
            z0, z1 = c.z_range(spec.face_width)
            if not (-half <= z0 and z1 <= half and z1 - z0 >= MIN_SLAB_MM):
                raise DefectError(f"chips[{i}].z_mm={c.z_mm} must lie in [{-half:g}, {half:g}] mm, at least {MIN_SLAB_MM} mm long")
        ends = sorted({-half, half, *(z for c in self.chips for z in c.z_range(spec.face_width))})
        if any(b - a < MIN_SLAB_MM for a, b in zip(ends[:-1], ends[1:], strict=True)):
            raise DefectError(f"chips[].z_mm: chip ends {ends} must be equal or at least {MIN_SLAB_MM} mm apart (and from the faces)")
        return spec

    def mesh(self, nominal: GearSpec, flank_points: int = 40, layer_mm: float = 1.0):
        """Watertight ``open3d`` mesh of the as-built gear in the turntable frame."""
        spec = self.check(nominal)
        land_step = 0.15 * spec.module
        keys = {(c.tooth, SIDE_SIGN[c.side]): c.size_mm for c in self.chips}
        sec = spec.section(
            flank_points,
            tooth_shift=self.tooth_shift(spec),
            flank_offset=partial(self.flank_offset, spec) if self._has_flank_offset else None,
            flank_marks={key: spec.tip_radius - size for key, size in keys.items()},
            tip_marks=keys,
        )
        n_o = len(sec.xy)
        parts, cuts = [sec.xy], []  # per chip: (first, last) outline row of the cut, new rows between
        count = n_o
        for c in self.chips:
            key = (c.tooth, SIDE_SIGN[c.side])
            i0, i1 = sorted((sec.marks[("flank", *key)], sec.marks[("tip", *key)]))
            p0, p1 = sec.xy[i0], sec.xy[i1]
            n = max(1, math.ceil(float(np.linalg.norm(p1 - p0)) / land_step))
            parts.append(p0 + (p1 - p0) * (np.arange(1, n) / n)[:, None])
            cuts.append((i0, i1, count + np.arange(n - 1)))
            count += n - 1
        bore = bore_loop(spec)
        hole = None if bore is None else count + np.arange(len(bore))
        xy = np.concatenate(parts if bore is None else [*parts, bore])

        half = spec.face_width / 2
        ranges = [c.z_range(spec.face_width) for c in self.chips]
        ends = sorted({-half, half, *(z for r in ranges for z in r)})
        slabs = []
        for z0, z1 in zip(ends[:-1], ends[1:], strict=True):
            active = sorted(cut for cut, (a, b) in zip(cuts, ranges, strict=True) if a <= z0 and b >= z1)
            slabs.append((z0, z1, _replace_chains(n_o, active)))
        steps = []
        for (i0, i1, inner), (a, b) in zip(cuts, ranges, strict=True):
            polygon = np.concatenate([np.arange(i0, i1 + 1), inner[::-1]])  # corner, then back along the cut
            steps += [(a, polygon, True)] if a > -half else []
            steps += [(b, polygon, False)] if b < half else []
        mesh = extrude(xy, slabs, hole, steps, layer_mm=layer_mm)
        return mesh.translate((*self.center, 0.0))

    # --- the answer -------------------------------------------------------------------------
    def flank_positions_um(self, spec: GearSpec) -> dict[str, np.ndarray]:
        """Each flank's position on the pitch circle, along it, vs. its ideal place, µm (+: +theta).

        Tooth turn plus the flank's normal offset there (``d r / r_b`` along the circle).
        Relative to the gear's own axis: eccentricity comes on top when measured about the table.
        """
        rp, rb = spec.pitch_radius, spec.base_radius
        u = 1e3 * self.tooth_shift(spec) * rp
        out = {}
        for name, s in SIDE_SIGN.items():
            d = np.array([float(self.flank_offset(spec, k, s, rp)) for k in range(spec.teeth)])
            out[name] = u + s * 1e3 * d * rp / rb
        return out

    def truth(self, nominal: GearSpec) -> dict:
        """What a recording states as the answer: the defects and what an inspector reads from them.

        Pitch (ISO 1328-1 names, per flank side, at the pitch circle, about the gear axis):
        ``single_pitch_um[k]`` = position of tooth k minus that of tooth k-1 (fp);
        ``total_cumulative_pitch_um`` = max - min of the positions (Fp). Runout from the
        eccentricity alone (first order): the range of ``e cos(theta_gap - phi)`` over the gaps.
        """
        spec = self.check(nominal)
        pos = self.flank_positions_um(spec)
        gaps = (np.arange(spec.teeth) + 0.5) * spec.pitch_angle
        radial = self.eccentricity_um * np.cos(gaps - math.radians(self.eccentricity_deg))
        return {
            "gear": spec.model_dump(),
            "defects": self.model_dump(mode="json"),
            "eccentricity_mm": self.center.tolist(),
            "flank_position_um": {s: p.tolist() for s, p in pos.items()},
            "single_pitch_um": {s: (p - np.roll(p, 1)).tolist() for s, p in pos.items()},
            "total_cumulative_pitch_um": {s: float(p.max() - p.min()) for s, p in pos.items()},
            "runout_from_eccentricity_um": float(radial.max() - radial.min()),
            "chipped_teeth": sorted({c.tooth for c in self.chips}),
            "worn_flanks": [[w.tooth, w.side] for w in self.wear],
        }


def true_mesh(nominal: GearSpec, defects: GearDefects | None = None, flank_points: int = 40, layer_mm: float = 1.0):
    """The as-built gear's mesh: ``nominal`` with ``defects`` (the nominal mesh when there are none)."""
    if defects is None or defects.empty:
        return nominal.mesh(flank_points=flank_points, layer_mm=layer_mm)
    return defects.mesh(nominal, flank_points=flank_points, layer_mm=layer_mm)


def _replace_chains(n: int, cuts: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """Outline rows ``0..n-1`` with the rows strictly between each cut's ends replaced by the cut."""
    pieces, pos = [], 0
    for i0, i1, inner in cuts:
        pieces += [np.arange(pos, i0 + 1), inner]
        pos = i1
    pieces.append(np.arange(pos, n))
    return np.concatenate(pieces)


def _fields(option: str, text: str, form: str, least: int, most: int) -> list:
    """``TOOTH:NUMBER[:SIDE[:NUMBER:NUMBER]]`` split into typed fields, or a DefectError naming the option."""
    parts = [p.strip() for p in text.split(":")]
    try:
        if not least <= len(parts) <= most:
            raise ValueError
        return [int(parts[0]), float(parts[1]), *parts[2:3], *(float(p) for p in parts[3:])]
    except ValueError:
        raise DefectError(f"{option} {text!r}: expected {form}") from None


def _errors(exc: ValidationError) -> str:
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'defects'}: {e['msg']}" for e in exc.errors())
