"""Write the STEP sample `step_bracket/bracket.step` by hand: three named solids in one file.

No CAD kernel is needed: the solids are exact B-rep (planes and cylinders, AP214 entities) written
out here, and OpenCASCADE (through cascadio) reads them back. Millimetres, as CAD tools write STEP.

  plate    60 x 40 x 8 mm, a 10 mm hole at (15, 0) and a 10 mm boss 4 mm high at (-20, 10)
  pin      10 mm across, 30 mm long, goes through the hole, flush with the plate's underside
  bushing  20 mm across, 10 mm bore, 12 mm high, on the pin, resting on the plate

Run by `python sample_assemblies/generate.py`, which writes every sample.
"""

from __future__ import annotations

import math
from pathlib import Path

HOLE = (15.0, 0.0, 5.0)  # x, y, radius of the plate's through hole (and the pin)
BOSS = (-20.0, 10.0, 5.0, 4.0)  # x, y, radius, height above the plate's top


class StepWriter:
    """Numbered entities of one ISO 10303-21 file; every `add` returns the entity's '#n'."""

    def __init__(self):
        self.lines: list[str] = []

    def add(self, text: str) -> str:
        self.lines.append(text)
        return f"#{len(self.lines)}"

    def point(self, p) -> str:
        return self.add(f"CARTESIAN_POINT('',({','.join(_f(v) for v in p)}))")

    def direction(self, d) -> str:
        return self.add(f"DIRECTION('',({','.join(_f(v) for v in d)}))")

    def frame(self, origin, axis=(0, 0, 1), ref=(1, 0, 0)) -> str:
        return self.add(f"AXIS2_PLACEMENT_3D('',{self.point(origin)},{self.direction(axis)},{self.direction(ref)})")

    def vertex(self, p) -> str:
        return self.add(f"VERTEX_POINT('',{self.point(p)})")

    def line_edge(self, v0: str, v1: str, p0, p1) -> str:
        d = [b - a for a, b in zip(p0, p1)]
        n = math.sqrt(sum(x * x for x in d))
        vec = self.add(f"VECTOR('',{self.direction([x / n for x in d])},{_f(n)})")
        return self.add(f"EDGE_CURVE('',{v0},{v1},{self.add(f'LINE({chr(39)}{chr(39)},{self.point(p0)},{vec})')},.T.)")

    def circle_edge(self, cx: float, cy: float, z: float, r: float) -> tuple[str, str]:
        """A full circle about +z, counter-clockwise seen from above, closed on its vertex at angle 0."""
        v = self.vertex((cx + r, cy, z))
        circle = self.add(f"CIRCLE('',{self.frame((cx, cy, z))},{_f(r)})")
        return self.add(f"EDGE_CURVE('',{v},{v},{circle},.T.)"), v

    def loop(self, edges: list[tuple[str, bool]]) -> str:
        oes = [self.add(f"ORIENTED_EDGE('',*,*,{e},{'.T.' if s else '.F.'})") for e, s in edges]
        return self.add(f"EDGE_LOOP('',({','.join(oes)}))")

    def face(self, surface: str, loops: list[str], same_sense: bool = True) -> str:
        bounds = [self.add(f"FACE_OUTER_BOUND('',{loops[0]},.T.)")]
        bounds += [self.add(f"FACE_BOUND('',{lp},.T.)") for lp in loops[1:]]
        return self.add(f"ADVANCED_FACE('',({','.join(bounds)}),{surface},{'.T.' if same_sense else '.F.'})")

    def plane(self, origin, normal) -> str:
        ref = (1, 0, 0) if abs(normal[0]) < 0.9 else (0, 1, 0)
        return self.add(f"PLANE('',{self.frame(origin, normal, ref)})")

    def cylinder_face(self, cx, cy, z0, z1, r, bottom, top, outward: bool) -> str:
        """The side of a cylinder between two circle edges (bottom, top: (edge, vertex)), with a seam."""
        seam = self.line_edge(bottom[1], top[1], (cx + r, cy, z0), (cx + r, cy, z1))
        surface = self.add(f"CYLINDRICAL_SURFACE('',{self.frame((cx, cy, z0))},{_f(r)})")
        if outward:
            lp = self.loop([(bottom[0], True), (seam, True), (top[0], False), (seam, False)])
        else:  # a hole: the face looks at the axis
            lp = self.loop([(top[0], True), (seam, False), (bottom[0], False), (seam, True)])
        return self.face(surface, [lp], same_sense=outward)


def _f(v: float) -> str:
    s = f"{float(v):.6f}".rstrip("0")
    return s + "0" if s.endswith(".") else s


def _disc(w: StepWriter, circle, z: float, up: bool, holes=()) -> str:
    """A flat face bounded by a circle edge (and holes' circle edges), facing +z when `up`."""
    loops = [w.loop([(circle[0], up)])] + [w.loop([(h[0], not up)]) for h in holes]
    return w.face(w.plane((0, 0, z), (0, 0, 1 if up else -1)), loops)


def cylinder_solid(w: StepWriter, cx, cy, z0, z1, r, bore: float = 0.0) -> list[str]:
    """Faces of a cylinder (a tube when `bore` > 0) along +z."""
    bot, top = w.circle_edge(cx, cy, z0, r), w.circle_edge(cx, cy, z1, r)
    faces = [w.cylinder_face(cx, cy, z0, z1, r, bot, top, outward=True)]
    holes_b, holes_t = [], []
    if bore > 0:
        hb, ht = w.circle_edge(cx, cy, z0, bore), w.circle_edge(cx, cy, z1, bore)
        faces.append(w.cylinder_face(cx, cy, z0, z1, bore, hb, ht, outward=False))
        holes_b, holes_t = [hb], [ht]
    return faces + [_disc(w, bot, z0, up=False, holes=holes_b), _disc(w, top, z1, up=True, holes=holes_t)]


def plate_solid(w: StepWriter) -> list[str]:
    sx, sy, h = 30.0, 20.0, 8.0
    corners = [(-sx, -sy), (sx, -sy), (sx, sy), (-sx, sy)]  # counter-clockwise from above
    vb = [w.vertex((x, y, 0.0)) for x, y in corners]
    vt = [w.vertex((x, y, h)) for x, y in corners]
    bottom_e, top_e, up_e = [], [], []
    for i in range(4):
        j = (i + 1) % 4
        (x0, y0), (x1, y1) = corners[i], corners[j]
        bottom_e.append(w.line_edge(vb[i], vb[j], (x0, y0, 0.0), (x1, y1, 0.0)))
        top_e.append(w.line_edge(vt[i], vt[j], (x0, y0, h), (x1, y1, h)))
        up_e.append(w.line_edge(vb[i], vt[i], (x0, y0, 0.0), (x0, y0, h)))
    hx, hy, hr = HOLE
    hole_b, hole_t = w.circle_edge(hx, hy, 0.0, hr), w.circle_edge(hx, hy, h, hr)
    bx, by, br, bh = BOSS
    boss_b, boss_t = w.circle_edge(bx, by, h, br), w.circle_edge(bx, by, h + bh, br)
    faces = [
        w.face(w.plane((0, 0, 0), (0, 0, -1)), [w.loop([(e, False) for e in reversed(bottom_e)]),
                                                w.loop([(hole_b[0], True)])]),
        w.face(w.plane((0, 0, h), (0, 0, 1)), [w.loop([(e, True) for e in top_e]), w.loop([(hole_t[0], False)]),
                                               w.loop([(boss_b[0], False)])]),
        w.cylinder_face(hx, hy, 0.0, h, hr, hole_b, hole_t, outward=False),
        w.cylinder_face(bx, by, h, h + bh, br, boss_b, boss_t, outward=True),
        _disc(w, boss_t, h + bh, up=True),
    ]
    for i in range(4):
        j = (i + 1) % 4
        (x0, y0), (x1, y1) = corners[i], corners[j]
        normal = (y1 - y0, -(x1 - x0), 0.0)
        n = math.hypot(normal[0], normal[1])
        faces.append(w.face(w.plane((x0, y0, 0.0), (normal[0] / n, normal[1] / n, 0.0)),
                            [w.loop([(bottom_e[i], True), (up_e[j], True), (top_e[i], False), (up_e[i], False)])]))
    return faces


def step_text(solids: dict[str, list[str]], w: StepWriter) -> str:
    """The whole file: each solid its own named product (CAD tools' part names)."""
    mm = w.add("( LENGTH_UNIT() NAMED_UNIT(*) SI_UNIT(.MILLI.,.METRE.) )")
    rad = w.add("( NAMED_UNIT(*) PLANE_ANGLE_UNIT() SI_UNIT($,.RADIAN.) )")
    sr = w.add("( NAMED_UNIT(*) SI_UNIT($,.STERADIAN.) SOLID_ANGLE_UNIT() )")
    unc = w.add(f"UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-07),{mm},'distance_accuracy_value','')")
    ctx = w.add(f"( GEOMETRIC_REPRESENTATION_CONTEXT(3) GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT(({unc})) "
                f"GLOBAL_UNIT_ASSIGNED_CONTEXT(({mm},{rad},{sr})) REPRESENTATION_CONTEXT('','') )")
    app = w.add("APPLICATION_CONTEXT('core data for automotive mechanical design processes')")
    w.add(f"APPLICATION_PROTOCOL_DEFINITION('international standard','automotive_design',2000,{app})")
    pctx = w.add(f"PRODUCT_CONTEXT('',{app},'mechanical')")
    dctx = w.add(f"PRODUCT_DEFINITION_CONTEXT('part definition',{app},'design')")
    for name, faces in solids.items():
        shell = w.add(f"CLOSED_SHELL('',({','.join(faces)}))")
        brep = w.add(f"MANIFOLD_SOLID_BREP('{name}',{shell})")
        rep = w.add(f"ADVANCED_BREP_SHAPE_REPRESENTATION('{name}',({brep},{w.frame((0, 0, 0))}),{ctx})")
        prod = w.add(f"PRODUCT('{name}','{name}','',({pctx}))")
        form = w.add(f"PRODUCT_DEFINITION_FORMATION('','',{prod})")
        pdef = w.add(f"PRODUCT_DEFINITION('design','',{form},{dctx})")
        shape = w.add(f"PRODUCT_DEFINITION_SHAPE('','',{pdef})")
        w.add(f"SHAPE_DEFINITION_REPRESENTATION({shape},{rep})")
    head = ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('apose_studio STEP sample'),'2;1');\n"
            "FILE_NAME('bracket.step','2026-01-01T00:00:00',(''),(''),'sample_assemblies/make_step.py','','');\n"
            "FILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));\nENDSEC;\nDATA;\n")
    body = "".join(f"#{i + 1}={line};\n" for i, line in enumerate(w.lines))
    return head + body + "ENDSEC;\nEND-ISO-10303-21;\n"


ASSEMBLY_YAML = """\
# STEP sample: three solids of one STEP file, placed by mates. Generated by sample_assemblies/make_step.py.
format: apose-assembly/1
name: step_bracket
units: mm
parts:
  plate:                  # `solid` picks one named solid of a STEP file with several
    mesh: bracket.step
    solid: plate
    color: [0.55, 0.58, 0.62]
  pin:
    mesh: bracket.step
    solid: pin
    color: [0.85, 0.55, 0.1]
    symmetry: {axis: [0, 0, 1], order: 0}
  bushing:
    mesh: bracket.step
    solid: bushing
    color: [0.2, 0.6, 0.9]
    symmetry: {axis: [0, 0, 1], order: 0}
steps:
  - part: pin
    base: [plate]
    mates:
      - type: coaxial     # in the hole
        base: {point: [15, 0, 0], direction: [0, 0, 1]}
        part: {point: [0, 0, 0], direction: [0, 0, 1]}
      - type: aligned     # flush with the plate's underside
        base: {point: [0, 0, 0], normal: [0, 0, -1]}
        part: {point: [0, 0, 0], normal: [0, 0, -1]}
    approach: {direction: [0, 0, -1], distance: 40}
  - part: bushing
    base: [plate, pin]
    mates:
      - type: coaxial     # on the pin
        base: {part: pin, point: [0, 0, 0], direction: [0, 0, 1]}
        part: {point: [0, 0, 0], direction: [0, 0, 1]}
      - type: contact     # resting on the plate's top
        base: {point: [0, 0, 8], normal: [0, 0, 1]}
        part: {point: [0, 0, 0], normal: [0, 0, -1]}
    approach: {direction: [0, 0, -1], distance: 30}
"""


def generate(out: Path) -> list[Path]:
    folder = out / "step_bracket"
    folder.mkdir(parents=True, exist_ok=True)
    w = StepWriter()
    solids = {"plate": plate_solid(w), "pin": cylinder_solid(w, 0.0, 0.0, 0.0, 30.0, HOLE[2]),
              "bushing": cylinder_solid(w, 0.0, 0.0, 0.0, 12.0, 10.0, bore=5.0)}
    (folder / "bracket.step").write_text(step_text(solids, w))
    (folder / "assembly.yaml").write_text(ASSEMBLY_YAML)
    return [folder / "bracket.step", folder / "assembly.yaml"]
