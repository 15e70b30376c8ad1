"""Involute spur gear: analytic geometry and a watertight triangle mesh.

The gear lies in the turntable frame: axis along z, face centred on z = 0. Tooth 0 is
centred on the +x axis. All lengths in mm.

References
----------
ISO 21771 (cylindrical involute gears), ISO 53 (basic rack, root fillet 0.38 m).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


def involute(alpha: np.ndarray | float) -> np.ndarray | float:
    """``inv(alpha) = tan(alpha) - alpha``."""
    return np.tan(alpha) - alpha


class GearSpec(BaseModel):
    """Parameters of an external involute spur gear (ISO 21771 names)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    module: float = Field(2.0, gt=0.05, le=50, description="module m, mm")
    teeth: int = Field(20, ge=6, le=400, description="number of teeth z")
    pressure_angle_deg: float = Field(20.0, ge=10, le=35, description="pressure angle, degrees")
    face_width: float = Field(20.0, gt=0, le=500, description="face width b, mm")
    addendum_coef: float = Field(1.0, ge=0.5, le=1.5, description="addendum h_a* (x m)")
    dedendum_coef: float = Field(1.25, ge=0.6, le=1.8, description="dedendum h_f* (x m)")
    fillet_coef: float = Field(0.38, ge=0.0, le=0.6, description="root fillet radius rho_f* (x m)")
    profile_shift: float = Field(0.0, ge=-0.5, le=1.0, description="profile shift coefficient x")
    bore: float = Field(10.0, ge=0, description="bore diameter, mm (0 for none)")

    @model_validator(mode="after")
    def _check(self) -> GearSpec:
        if self.root_radius <= 0:
            raise ValueError(f"dedendum_coef={self.dedendum_coef} gives a root radius <= 0")
        if self.bore / 2 >= self.root_radius * 0.9:
            raise ValueError(
                f"bore={self.bore} mm must be below 0.9 x root diameter ({1.8 * self.root_radius:.2f} mm)"
            )
        if self.tip_half_angle <= 0:
            raise ValueError("teeth come to a point below the tip circle: reduce addendum_coef or profile_shift")
        return self

    # --- radii and angles -------------------------------------------------------------
    @property
    def pressure_angle(self) -> float:
        return math.radians(self.pressure_angle_deg)

    @property
    def pitch_angle(self) -> float:
        """Angle between neighbouring teeth, rad (2 pi / z)."""
        return 2 * math.pi / self.teeth

    @property
    def pitch_radius(self) -> float:
        return self.module * self.teeth / 2

    @property
    def base_radius(self) -> float:
        return self.pitch_radius * math.cos(self.pressure_angle)

    @property
    def tip_radius(self) -> float:
        return self.pitch_radius + (self.addendum_coef + self.profile_shift) * self.module

    @property
    def root_radius(self) -> float:
        return self.pitch_radius - (self.dedendum_coef - self.profile_shift) * self.module

    @property
    def pitch_thickness(self) -> float:
        """Circular tooth thickness on the pitch circle, ``m (pi/2 + 2 x tan alpha)``."""
        return self.module * (math.pi / 2 + 2 * self.profile_shift * math.tan(self.pressure_angle))

    def half_angle(self, radius: np.ndarray | float) -> np.ndarray | float:
        """Half the angular tooth thickness at ``radius`` (>= base radius), rad."""
        psi = self.pitch_thickness / (2 * self.pitch_radius)
        alpha_r = np.arccos(np.clip(self.base_radius / np.asarray(radius, dtype=float), -1, 1))
        return psi + involute(self.pressure_angle) - involute(alpha_r)

    def thickness_at(self, radius: float) -> float:
        """Circular (arc) tooth thickness at ``radius``, mm."""
        return 2 * float(self.half_angle(radius)) * radius

    @property
    def tip_half_angle(self) -> float:
        return float(self.half_angle(self.tip_radius))

    # --- outline --------------------------------------------------------------------------
    def outline(self, flank_points: int = 40, fillet_points: int = 10, land_step: float | None = None) -> np.ndarray:
        """Closed counter-clockwise outline ``(N, 2)`` of the gear's transverse section.

        Involute flanks are sampled uniformly in roll angle (denser near the base circle,
        where curvature is high); below the base circle the flank is radial, joined to the
        root circle by a circular fillet of radius ``fillet_coef * m``.
        """
        return self.section(flank_points, fillet_points, land_step).xy

    def section(
        self,
        flank_points: int = 40,
        fillet_points: int = 10,
        land_step: float | None = None,
        *,
        tooth_shift: np.ndarray | None = None,
        flank_offset: FlankOffset | None = None,
        flank_marks: dict[tuple[int, int], float] | None = None,
        tip_marks: dict[tuple[int, int], float] | None = None,
    ) -> Section:
        """The outline of :meth:`outline`, optionally with per-tooth deviations (as-built gears).

        ``tooth_shift`` (z,) rotates each tooth by its own angle (rad, + counter-clockwise);
        ``flank_offset(tooth, side, radius)`` moves a flank along its normal (mm, + adds
        material; ``side`` -1 is the flank on the tooth's -theta side, +1 the +theta side).
        An involute moved by ``d`` along its normal is the involute turned by ``d / r_b``, so
        the offset enters as a change of that flank's half angle. ``flank_marks[(tooth,
        side)]`` (a radius) and ``tip_marks[(tooth, side)]`` (arc length from that tip corner)
        put a vertex exactly there; ``Section.marks`` says where they ended up.
        """
        land_step = land_step or 0.15 * self.module
        shift = np.zeros(self.teeth) if tooth_shift is None else np.asarray(tooth_shift, dtype=float)
        flank_marks, tip_marks = flank_marks or {}, tip_marks or {}
        rb, ra, rf = self.base_radius, self.tip_radius, self.root_radius
        r_start = max(rb, rf)
        t0, ta = math.sqrt(max((r_start / rb) ** 2 - 1, 0.0)), math.sqrt((ra / rb) ** 2 - 1)
        half_base = float(self.half_angle(r_start))
        gap_half = self.pitch_angle / 2 - half_base  # half angular width of the gap at r_start

        # Fillet in polar coordinates relative to the flank line at angle 0 (gap on +theta side).
        fillet: list[tuple[float, float]] = []  # (r, dtheta), from flank down to the root circle
        rho = self.fillet_coef * self.module
        if rf < rb and rho > 0:
            rho = min(rho, (rb - rf) * 0.95, rf * math.sin(gap_half) * 0.9)
            gamma = math.asin(rho / (rf + rho))
            cx, cy = (rf + rho) * math.cos(gamma), (rf + rho) * math.sin(gamma)
            # walk the arc clockwise from the line tangent point (cx, 0) to the root point
            start = -math.pi / 2
            end = math.atan2(rf * math.sin(gamma) - cy, rf * math.cos(gamma) - cx)
            if end > start:
                end -= 2 * math.pi
            ang = np.linspace(start, end, fillet_points)
            px, py = cx + rho * np.cos(ang), cy + rho * np.sin(ang)
            fillet = list(zip(np.hypot(px, py), np.arctan2(py, px), strict=True))
            radial_top, radial_bottom = rb, (rf + rho) * math.cos(gamma)
            root_half_offset = gamma
        else:
            radial_top, radial_bottom = rb, rf
            root_half_offset = 0.0
        radial = np.linspace(radial_top, radial_bottom, max(2, int(math.ceil((radial_top - radial_bottom) / land_step)) + 1))
        # below the involute (radial line, fillet): (r, angle from the tooth centre), root to flank
        lower = [(r, half_base + d) for r, d in reversed(fillet)]
        if rf < rb:
            lower += [(r, half_base) for r in radial[::-1][1:]]

        pts: list[tuple] = []  # (r, theta, mark key or None), tooth after tooth from its -theta fillet
        for k in range(self.teeth):
            c = k * self.pitch_angle + shift[k]
            flank: dict[int, list[tuple]] = {}  # side -> points from the involute start to the tip
            for side in (-1, 1):
                mark = flank_marks.get((k, side))
                t_mark = [] if mark is None else [math.sqrt((mark / rb) ** 2 - 1)]
                roll = _spaced(t0, ta, flank_points, t_mark)
                r = rb * np.sqrt(1 + roll**2)
                h = np.asarray(self.half_angle(r), dtype=float)
                if flank_offset is not None:
                    h = h + np.asarray(flank_offset(k, side, r), dtype=float) / rb
                keys = [("flank", k, side) if t_mark and t == t_mark[0] else None for t in roll]
                flank[side] = [(ri, c + side * hi, key) for ri, hi, key in zip(r, h, keys, strict=True)]
            a_lo, a_hi = flank[-1][-1][1], flank[1][-1][1]  # tip corners
            marks = {a_lo + tip_marks[(k, -1)] / ra: ("tip", k, -1)} if (k, -1) in tip_marks else {}
            if (k, 1) in tip_marks:
                marks[a_hi - tip_marks[(k, 1)] / ra] = ("tip", k, 1)
            tip_n = max(2, int(math.ceil((a_hi - a_lo) * ra / land_step)) + 1)
            tip = [(ra, a, marks.get(a)) for a in _spaced(a_lo, a_hi, tip_n, sorted(marks))[1:-1]]
            c_next = (k + 1) * self.pitch_angle + shift[(k + 1) % self.teeth]
            root_a0 = c + half_base + root_half_offset
            root_a1 = c_next - half_base - root_half_offset
            root_n = max(2, int(math.ceil((root_a1 - root_a0) * rf / land_step)) + 1)
            pts += [(r, c - a, None) for r, a in lower] + flank[-1] + tip + flank[1][::-1]
            pts += [(r, c + a, None) for r, a in reversed(lower)]
            pts += [(rf, a, None) for a in np.linspace(root_a0, root_a1, root_n)[1:-1]]
        rt = np.asarray([p[:2] for p in pts])
        xy = np.stack([rt[:, 0] * np.cos(rt[:, 1]), rt[:, 0] * np.sin(rt[:, 1])], axis=1)
        # drop consecutive duplicates (flank/fillet joins)
        keep = np.ones(len(xy), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9
        new_index = np.cumsum(keep) - 1
        found = {p[2]: int(new_index[i]) for i, p in enumerate(pts) if p[2] is not None}
        return Section(xy[keep], found)

    # --- mesh -----------------------------------------------------------------------------
    def mesh(self, flank_points: int = 40, layer_mm: float = 1.0):
        """Watertight ``open3d.geometry.TriangleMesh`` of the gear (outward normals)."""
        return gear_mesh(self, flank_points=flank_points, layer_mm=layer_mm)


FlankOffset = Callable[[int, int, np.ndarray], np.ndarray]
"""``(tooth, side, radius) -> normal offset`` of a flank, mm; + adds material."""


@dataclass(frozen=True)
class Section:
    """A transverse section: closed counter-clockwise outline and the vertices asked for."""

    xy: np.ndarray  # (N, 2) mm
    marks: dict[tuple[str, int, int], int]  # ("flank" | "tip", tooth, side) -> row of xy


def _spaced(lo: float, hi: float, n: int, through: list[float] | tuple[float, ...] = ()) -> np.ndarray:
    """``n`` values from ``lo`` to ``hi`` (both included), as even as possible, that hit ``through``."""
    knots = [lo, *through, hi]
    out = [np.array([lo])]
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        m = max(1, round((n - 1) * (b - a) / (hi - lo)))
        out.append(np.linspace(a, b, m + 1)[1:])
    return np.concatenate(out)


def _cap_triangulation(outline: np.ndarray, bore_pts: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Quality constrained Delaunay triangulation of the section (no boundary Steiner points).

    Input vertices come first in the output, in their order; interior points follow.
    """
    import triangle

    n_o = len(outline)
    segs = [np.stack([np.arange(n_o), (np.arange(n_o) + 1) % n_o], axis=1)]
    verts = [outline]
    holes = None
    if bore_pts is not None:
        n_b = len(bore_pts)
        segs.append(n_o + np.stack([np.arange(n_b), (np.arange(n_b) + 1) % n_b], axis=1))
        verts.append(bore_pts)
        holes = np.array([[0.0, 0.0]])
    data = {"vertices": np.concatenate(verts), "segments": np.concatenate(segs)}
    if holes is not None:
        data["holes"] = holes
    tri = triangle.triangulate(data, "pq25Y")
    return tri["vertices"], tri["triangles"]


def bore_loop(spec: GearSpec) -> np.ndarray | None:
    """The bore's polygon ``(n, 2)``, clockwise (a hole in the counter-clockwise section), or None."""
    if spec.bore <= 0:
        return None
    n_b = max(48, int(math.ceil(math.pi * spec.bore / (0.5 * spec.module))))
    a = np.linspace(0, 2 * math.pi, n_b, endpoint=False)
    return np.stack([spec.bore / 2 * np.cos(-a), spec.bore / 2 * np.sin(-a)], axis=1)


def gear_mesh(spec: GearSpec, flank_points: int = 40, layer_mm: float = 1.0):
    """Extrude the gear section along z into a closed mesh; caps share the wall vertices."""
    outline = spec.outline(flank_points=flank_points)
    bore = bore_loop(spec)
    xy = outline if bore is None else np.concatenate([outline, bore])
    hole = None if bore is None else len(outline) + np.arange(len(bore))
    half = spec.face_width / 2
    return extrude(xy, [(-half, half, np.arange(len(outline)))], hole, layer_mm=layer_mm)


def extrude(
    xy: np.ndarray,
    slabs: Sequence[tuple[float, float, np.ndarray]],
    hole: np.ndarray | None = None,
    steps: Sequence[tuple[float, np.ndarray, bool]] = (),
    layer_mm: float = 1.0,
):
    """Closed ``open3d`` mesh of a prism whose section may change from one z-slab to the next.

    ``xy`` (P, 2) holds every section vertex; ``slabs`` are ``(z0, z1, loop)`` from bottom to
    top, each ``loop`` a counter-clockwise outline of indices into ``xy``; ``hole`` a clockwise
    loop (the bore) through all slabs. Where the outline changes between slabs, ``steps`` give
    the faces that close the mesh: ``(z, polygon, up)``, polygon counter-clockwise, ``up`` when
    the face looks towards +z. Vertices at the same z are shared, so walls, caps and steps meet
    edge to edge; walls are split into layers of at most ``layer_mm``.
    """
    import open3d as o3d

    verts: list[np.ndarray] = []
    count = 0
    levels: dict[float, np.ndarray] = {}  # z -> index of each xy row's vertex at that z (-1: none yet)

    def at(z: float, ids: np.ndarray) -> np.ndarray:
        nonlocal count
        index = levels.setdefault(z, np.full(len(xy), -1, np.int64))
        new = ids[index[ids] < 0]
        index[new] = count + np.arange(len(new))
        verts.append(np.column_stack([xy[new], np.full(len(new), z)]))
        count += len(new)
        return index[ids]

    def face(z: float, boundary: np.ndarray, inner: np.ndarray | None, up: bool) -> np.ndarray:
        v, t = _cap_triangulation(xy[boundary], None if inner is None else xy[inner])
        ids = boundary if inner is None else np.concatenate([boundary, inner])
        nonlocal count
        index = np.concatenate([at(z, ids), count + np.arange(len(v) - len(ids))])
        verts.append(np.column_stack([v[len(ids):], np.full(len(v) - len(ids), z)]))
        count += len(v) - len(ids)
        return index[t] if up else index[t[:, ::-1]]

    tris = []
    for z0, z1, loop in slabs:
        zs = np.linspace(z0, z1, max(1, int(math.ceil((z1 - z0) / layer_mm - 1e-9))) + 1)
        for ring in [loop] if hole is None else [loop, hole]:
            for lo, hi in zip(zs[:-1], zs[1:], strict=True):
                i0, j0 = at(float(lo), ring), at(float(hi), ring)
                i1, j1 = np.roll(i0, -1), np.roll(j0, -1)
                # loop is CCW for the outline (outward normals) and CW for the bore (normals into the hole)
                tris += [np.stack([i0, i1, j1], axis=1), np.stack([i0, j1, j0], axis=1)]
    tris.append(face(slabs[0][0], slabs[0][2], hole, up=False))
    tris.append(face(slabs[-1][1], slabs[-1][2], hole, up=True))
    tris += [face(z, polygon, None, up) for z, polygon, up in steps]
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(verts)),
        o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)),
    )
    mesh.compute_triangle_normals()
    mesh.compute_vertex_normals()
    return mesh
