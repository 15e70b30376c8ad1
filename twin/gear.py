"""Involute spur gear: analytic geometry and a watertight triangle mesh.

The gear lies in the turntable frame: axis along z, face centred on z = 0. Tooth 0 is
centred on the +x axis. All lengths in mm.

References
----------
ISO 21771 (cylindrical involute gears), ISO 53 (basic rack, root fillet 0.38 m).
"""

from __future__ import annotations

import math

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
        land_step = land_step or 0.15 * self.module
        rb, ra, rf = self.base_radius, self.tip_radius, self.root_radius
        r_start = max(rb, rf)
        t0, ta = math.sqrt(max((r_start / rb) ** 2 - 1, 0.0)), math.sqrt((ra / rb) ** 2 - 1)
        roll = np.linspace(t0, ta, flank_points)
        flank_r = rb * np.sqrt(1 + roll**2)
        flank_half = np.asarray(self.half_angle(flank_r), dtype=float)
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

        pts: list[tuple[float, float]] = []  # (r, theta) for one pitch, starting at a gap centre
        for k in range(self.teeth):
            c = k * self.pitch_angle
            # leading flank of tooth k (theta increasing from root to tip): gap is at -theta side
            lead: list[tuple[float, float]] = []
            for r, d in reversed(fillet):
                lead.append((r, c - half_base - d))
            if rf < rb:
                for r in radial[::-1][1:]:
                    lead.append((r, c - half_base))
            for r, h in zip(flank_r, flank_half, strict=True):
                lead.append((r, c - h))
            tip_n = max(2, int(math.ceil(2 * self.tip_half_angle * ra / land_step)) + 1)
            tip = [(ra, c + a) for a in np.linspace(-self.tip_half_angle, self.tip_half_angle, tip_n)[1:-1]]
            trail = [(r, 2 * c - th) for r, th in reversed(lead)]
            root_a0 = c + half_base + root_half_offset
            root_a1 = c + self.pitch_angle - half_base - root_half_offset
            root_n = max(2, int(math.ceil((root_a1 - root_a0) * rf / land_step)) + 1)
            root = [(rf, a) for a in np.linspace(root_a0, root_a1, root_n)[1:-1]]
            pts.extend(lead + tip + trail + root)
        rt = np.asarray(pts)
        xy = np.stack([rt[:, 0] * np.cos(rt[:, 1]), rt[:, 0] * np.sin(rt[:, 1])], axis=1)
        # drop consecutive duplicates (flank/fillet joins)
        keep = np.ones(len(xy), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9
        return xy[keep]

    # --- mesh -----------------------------------------------------------------------------
    def mesh(self, flank_points: int = 40, layer_mm: float = 1.0):
        """Watertight ``open3d.geometry.TriangleMesh`` of the gear (outward normals)."""
        return gear_mesh(self, flank_points=flank_points, layer_mm=layer_mm)


def _cap_triangulation(outline: np.ndarray, bore_pts: np.ndarray | None) -> np.ndarray:
    """Quality constrained Delaunay triangulation of the section (no boundary Steiner points)."""
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


def gear_mesh(spec: GearSpec, flank_points: int = 40, layer_mm: float = 1.0):
    """Extrude the gear section along z into a closed mesh; caps share the wall vertices."""
    import open3d as o3d

    outline = spec.outline(flank_points=flank_points)
    bore_pts = None
    if spec.bore > 0:
        n_b = max(48, int(math.ceil(math.pi * spec.bore / (0.5 * spec.module))))
        a = np.linspace(0, 2 * math.pi, n_b, endpoint=False)
        # clockwise so that the hole boundary has the opposite orientation of the outline
        bore_pts = np.stack([spec.bore / 2 * np.cos(-a), spec.bore / 2 * np.sin(-a)], axis=1)
    cap_v, cap_t = _cap_triangulation(outline, bore_pts)
    n_cap = len(cap_v)
    n_layers = max(1, int(math.ceil(spec.face_width / layer_mm)))
    zs = np.linspace(-spec.face_width / 2, spec.face_width / 2, n_layers + 1)

    # Boundary loops in cap-vertex indices (triangle keeps input vertices first, in order).
    loops = [np.arange(len(outline))]
    if bore_pts is not None:
        loops.append(len(outline) + np.arange(len(bore_pts)))

    verts = [np.column_stack([cap_v, np.full(n_cap, zs[0])]), np.column_stack([cap_v, np.full(n_cap, zs[-1])])]
    tris = [cap_t[:, ::-1], cap_t + n_cap]  # bottom faces -z (reversed), top faces +z
    offset = 2 * n_cap
    for loop in loops:
        ring = cap_v[loop]
        n = len(ring)
        # interior layers get their own vertices; first/last layers reuse the caps
        layer_index = [loop]  # bottom cap indices
        for z in zs[1:-1]:
            verts.append(np.column_stack([ring, np.full(n, z)]))
            layer_index.append(offset + np.arange(n))
            offset += n
        layer_index.append(loop + n_cap)
        for lo, hi in zip(layer_index[:-1], layer_index[1:], strict=True):
            i0, i1 = lo, np.roll(lo, -1)
            j0, j1 = hi, np.roll(hi, -1)
            # loop is CCW for the outline (outward normals) and CW for the bore (normals into the hole)
            tris.append(np.stack([i0, i1, j1], axis=1))
            tris.append(np.stack([i0, j1, j0], axis=1))
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(verts)),
        o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)),
    )
    mesh.compute_triangle_normals()
    mesh.compute_vertex_normals()
    return mesh
