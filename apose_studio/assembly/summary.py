"""`apose show`: an assembly summarised for people (mm, degrees) and as JSON (metres, 4x4 lists)."""

from __future__ import annotations

import numpy as np

from apose_studio.geometry import se3


def _fmt_pose(T: np.ndarray, scale_to_mm: float = 1000.0) -> str:
    t = T[:3, 3] * scale_to_mm
    q = se3.matrix_to_quat_wxyz(T[:3, :3])
    ang = se3.rotation_angle_deg(T[:3, :3])
    return (f"t = ({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}) mm, "
            f"q_wxyz = ({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f}), {ang:.1f}° rotation")


def show_json(asm, models) -> dict:
    """The `apose show --json` document (metres, 4x4 lists)."""
    return {
        "name": asm.name,
        "parts": {pid: {"mesh": str(p.mesh), "diameter": models[pid].diameter, "root": asm.root_of(pid),
                        "T_root_part": asm.T_root_part(pid).tolist(), **_roi_json(p, models[pid])}
                  for pid, p in asm.parts.items()},
        "steps": [_step_json(i, s) for i, s in enumerate(asm.steps)],
    }


def _roi_json(part, model) -> dict:
    """{"roi": ...} for a part that is a region (metres: kind, center, size or radius, the region's diameter), else {}."""
    if part.roi is None:
        return {}
    r = part.roi
    shape = {"size": list(r.size)} if r.kind == "box" else {"radius": r.radius}
    return {"roi": {"kind": r.kind, "center": list(r.center), **shape,
                    "region_diameter": float(np.linalg.norm(model.region.extents))}}


def region_text(part, model) -> str:
    """', region: box 64.0 x 50.0 x 40.0 mm at (...) mm' for a part with an roi, else ''."""
    if part.roi is None:
        return ""
    r = part.roi
    c = ", ".join(f"{v * 1000:.1f}" for v in r.center)
    shape = (f"box {' x '.join(f'{v * 1000:.1f}' for v in r.size)} mm" if r.kind == "box"
             else f"sphere {2000 * r.radius:.1f} mm across")
    return f", region (roi): {shape} at ({c}) mm, {np.linalg.norm(model.region.extents) * 1000:.1f} mm across"


def _step_json(i: int, s) -> dict:
    out = {"step": i + 1, "part": s.part, "base": list(s.base), "T_base_part": s.T_base_part.tolist()}
    if s.mates:  # T_base_part is then the mates' solution
        out["mates"] = [m.type for m in s.mates]
        out["free"] = list(s.free)
    if s.approach is not None:
        out["approach"] = {"direction": s.approach.direction.tolist(), "distance": s.approach.distance}
    return out


def show_text(asm, models) -> str:
    lines = [f"{asm.name}  ({asm.path})", f"units in file: {asm.units}", "", "parts:"]
    w = max(len(p) for p in asm.parts)
    for pid, p in asm.parts.items():
        m = models[pid]
        size = " x ".join(f"{v * 1000:.1f}" for v in m.size)
        root = "root" if pid in asm.roots else f"on {asm.root_of(pid)}"
        sym = ""
        if p.symmetry is not None:
            sym = f", {'continuous' if p.symmetry.order == 0 else str(p.symmetry.order) + '-fold'} symmetry"
        lines.append(f"  {pid:<{w}}  {p.mesh.name}  {size} mm, diameter {m.diameter * 1000:.1f} mm, {root}{sym}"
                     f"{region_text(p, m)}")
        if m.unit_warning:
            lines.append(f"  {'':<{w}}  warning: {m.unit_warning}")
    lines += ["", "steps:"]
    for i, s in enumerate(asm.steps):
        lines.append(f"  {i + 1}. place {s.part} on [{', '.join(s.base)}]")
        lines.append(f"     pose in {s.base[0]}: {_fmt_pose(s.T_base_part)}")
        if s.mates:
            lines.append(f"     from mates: {', '.join(m.type for m in s.mates)}; "
                         + ("the pose is fixed" if not s.free else "free: " + "; ".join(s.free)))
        if s.approach is not None:
            d = s.approach.direction
            lines.append(f"     approach: {s.approach.distance * 1000:.1f} mm along ({d[0]:+.3f}, {d[1]:+.3f}, {d[2]:+.3f})")
    lines += ["", "completed assembly (pose of each part in its root's frame):"]
    for root, members in asm.completed().items():
        for pid, T in members.items():
            lines.append(f"  {root} <- {pid:<{w}}  {_fmt_pose(T)}")
    return "\n".join(lines)
