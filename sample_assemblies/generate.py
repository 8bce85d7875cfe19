#!/usr/bin/env python3
"""Generate the project's sample assemblies (deterministic, re-runnable).

    python sample_assemblies/generate.py [--out sample_assemblies]

Three assemblies with real-looking geometry, in millimetres (to exercise unit handling):
  helical_gearbox/    casing, helical pinion, helical wheel, lid          (4 parts, 3 steps)
  planetary_reducer/  motor block, sun gear, ring-gear housing,
                      planet carrier with planets, cover                   (5 parts, 4 steps)
  step_bracket/       plate, pin, bushing: one STEP file (make_step.py)    (3 parts, 2 steps)
  desk_objects/       a tin box, a watering can, a hole punch and a toy duck, each a root with a
                      label to place on it: household objects at their real size, seen by a
                      Kinect v1 (LINEMOD's intrinsics), as on a real cluttered desk   (8 parts, 4 steps)
  engine_head/        an engine head with eight rocker-arm seats, each a region of interest
                      (`roi`) of the one head mesh and its own root, and an arm for each (16 parts, 8 steps)
The meshes are built with manifold3d (exact CSG, always watertight); gear teeth are extruded from a
2D involute-like profile, with a twist for the helical gears. The STEP file's B-rep is written by hand.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import trimesh
from manifold3d import CrossSection, JoinType, Manifold, OpType

HERE = Path(__file__).resolve().parent
SEGMENTS = 48  # circular segments for bores and bosses


# ----------------------------------------------------------------------------------- 2D profiles


def gear_profile(teeth: int, module: float, internal: bool = False, flank_points: int = 5) -> np.ndarray:
    """Closed outline (N, 2) of a gear: each tooth a curved flank up, a tip land, a flank down, a root land.

    The flank bulges like an involute (radius grows faster near the root). For the bore of an
    internal (ring) gear the outline's bumps are the ring's tooth spaces, so only the radii change.
    """
    r = module * teeth / 2
    r_tip, r_root = (r + 1.25 * module, r - module) if internal else (r + module, r - 1.25 * module)
    pitch = 2 * math.pi / teeth
    half = (math.pi * module / 2) / r / 2  # half the tooth (or space) angle at the pitch circle
    a_root, a_tip = half * 1.25, half * 0.55
    s = np.linspace(0, 1, flank_points)
    rad = r_root + (r_tip - r_root) * (1 - (1 - s) ** 1.6)
    ang = a_root + (a_tip - a_root) * s
    pts = []
    for i in range(teeth):
        c = i * pitch
        flank = [(c - a, rr) for a, rr in zip(ang, rad)] + [(c + a, rr) for a, rr in zip(ang[::-1], rad[::-1])]
        land = [(a, r_root) for a in np.linspace(c + a_root, c + pitch - a_root, 4)[1:-1]]
        pts += [(rr * math.cos(a), rr * math.sin(a)) for a, rr in flank + land]
    return np.array(pts)


def circle(radius: float, x: float = 0.0, y: float = 0.0) -> CrossSection:
    return CrossSection.circle(radius, SEGMENTS).translate((x, y))


def rect(w: float, h: float, x: float = 0.0, y: float = 0.0) -> CrossSection:
    return CrossSection.square((w, h), center=True).translate((x, y))


def rounded_rect(w: float, h: float, r: float) -> CrossSection:
    return rect(w - 2 * r, h - 2 * r).offset(r, JoinType.Round, circular_segments=SEGMENTS)


def prism(section: CrossSection, z0: float, z1: float, twist_deg: float = 0.0, divisions: int = 0) -> Manifold:
    return Manifold.extrude(section, z1 - z0, divisions, twist_deg).translate((0, 0, z0))


def cylinder(radius: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0) -> Manifold:
    return Manifold.cylinder(z1 - z0, radius, radius, SEGMENTS).translate((x, y, z0))


def union(*ms: Manifold) -> Manifold:
    return Manifold.batch_boolean(list(ms), OpType.Add)


# ----------------------------------------------------------------------------------- parts


def helical_gear(teeth: int, module: float, face: float, helix_deg: float, bore: float,
                 hub_r: float, keyway: bool) -> Manifold:
    """Helical gear centred on its origin (axis z, mid-face at z=0), with a bore, hub and keyway."""
    r_pitch = module * teeth / 2
    twist = math.degrees(face * math.tan(math.radians(helix_deg)) / r_pitch)
    body = prism(CrossSection([gear_profile(teeth, module)]), -face / 2, face / 2, twist, divisions=10)
    # lightening recess on both faces, a hub standing out 1.5 mm
    recess_r = r_pitch - 2.5 * module
    if recess_r > hub_r + 2:
        ring = circle(recess_r) - circle(hub_r)
        body = body - prism(ring, face / 2 - 2, face / 2 + 1) - prism(ring, -face / 2 - 1, -face / 2 + 2)
    body = body + cylinder(hub_r, -face / 2 - 1.5, face / 2 + 1.5)
    hole = circle(bore)
    if keyway:
        hole = hole + rect(bore * 0.5, bore * 0.9, x=0, y=bore * 0.75)
    return body - prism(hole, -face, face)


def gearbox_casing() -> Manifold:
    """Open-top casing 92 x 64 x 24 mm, origin at the bottom centre; shafts at x=-20 and x=+16."""
    outer = prism(rounded_rect(92, 64, 5), 0, 24)
    cavity = prism(rounded_rect(84, 56, 3), 4, 30)
    body = outer - cavity
    # bearing bosses with shaft pins for the two gears (z 4..7), pins up to z 20
    for x, r in ((-20.0, 9.0), (16.0, 11.0)):
        body = body + cylinder(r, 3.5, 7, x=x) + cylinder(3.9, 6, 20, x=x)
    # mounting ears with bolt holes (outside, at the floor)
    for x in (-52.0, 52.0):
        ear = prism(rect(14, 30, x=x), 0, 5) - cylinder(3.2, -1, 6, x=x)
        body = body + ear
    # input-shaft boss through the -x wall, only on one side: the casing is not 2-fold symmetric
    body = body + Manifold.cylinder(8, 8, 8, SEGMENTS).rotate((0, 90, 0)).translate((-50, 0, 14))
    body = body - Manifold.cylinder(20, 4, 4, SEGMENTS).rotate((0, 90, 0)).translate((-55, 0, 14))
    # oil drain plug on the +y wall near +x
    body = body + Manifold.cylinder(4, 4.5, 4.5, SEGMENTS).rotate((-90, 0, 0)).translate((30, 31, 6))
    # bolt holes for the lid in the four corners (blind, from the top)
    for x in (-40.0, 40.0):
        for y in (-26.0, 26.0):
            body = body + cylinder(4, 0, 24, x=x, y=y) - cylinder(1.6, 14, 25, x=x, y=y)
    return body


def gearbox_lid() -> Manifold:
    """Lid plate 92 x 64 x 4 mm with a locating lip below and bearing caps above; origin at its bottom."""
    plate = prism(rounded_rect(92, 64, 5), 0, 4)
    lip = prism(rounded_rect(83.4, 55.4, 2.7) - rounded_rect(79, 51, 1), -3, 0)
    for x in (-40.0, 40.0):
        for y in (-26.0, 26.0):
            lip = lip - cylinder(4.3, -4, 1, x=x, y=y)  # clear the casing's corner bolt bosses
    body = plate + lip
    for x, r in ((-20.0, 9.0), (16.0, 11.0)):
        body = body + cylinder(r, 4, 7, x=x)
    body = body + cylinder(5, 4, 12, x=30, y=-18) - cylinder(2, 6, 13, x=30, y=-18)  # breather
    for x in (-40.0, 40.0):
        for y in (-26.0, 26.0):
            body = body - cylinder(1.8, -1, 5, x=x, y=y) - cylinder(3.2, 3, 5, x=x, y=y)
    return body


def motor_block() -> Manifold:
    """NEMA-17-like stepper: 42.3 mm square, 40 mm long, chamfered, boss and 5 mm D-shaft; origin at bottom centre."""
    s = 42.3
    section = CrossSection([np.array([(-s / 2 + 4, -s / 2), (s / 2 - 4, -s / 2), (s / 2, -s / 2 + 4),
                                      (s / 2, s / 2 - 4), (s / 2 - 4, s / 2), (-s / 2 + 4, s / 2),
                                      (-s / 2, s / 2 - 4), (-s / 2, -s / 2 + 4)])])
    body = prism(section, 0, 40)
    # the seams between end caps and the stator stack
    for z in (8.0, 32.0):
        body = body - (prism(section, z - 0.4, z + 0.4) - prism(section.offset(-0.6, JoinType.Miter), z - 1, z + 1))
    body = body + cylinder(11, 40, 42)
    shaft = prism(circle(2.5) - rect(6, 3, y=2.5 + 1.5 - 0.5), 42, 62)
    body = body + shaft
    for x in (-15.5, 15.5):
        for y in (-15.5, 15.5):
            body = body - cylinder(1.5, 35, 41, x=x, y=y)
    # cable connector on one side
    body = body + prism(rect(16, 6, y=-s / 2 - 3), 2, 10)
    return body


def ring_housing() -> Manifold:
    """Square flange (42 x 42 x 4) and a ring gear (36 internal teeth, m=1) above it; origin at the flange bottom."""
    flange = prism(rounded_rect(42.3, 42.3, 4), 0, 4) - cylinder(12, -1, 5)
    for x in (-15.5, 15.5):
        for y in (-15.5, 15.5):
            flange = flange - cylinder(1.7, -1, 5, x=x, y=y) - cylinder(3, 2.5, 5, x=x, y=y)
    ring_section = circle(25) - CrossSection([gear_profile(36, 1.0, internal=True)])
    ring = prism(ring_section, 4, 22)
    ribs = union(*[prism(rect(4, 6, x=0, y=26).rotate(a), 4, 20) for a in (0, 90, 180, 270)])
    return flange + ring + ribs


def planet_carrier() -> Manifold:
    """Carrier plate with three 12-tooth planets (m=1) on pins and an output shaft; origin mid-planet."""
    planets = []
    for k in range(3):
        a = 2 * math.pi * k / 3
        x, y = 12 * math.cos(a), 12 * math.sin(a)
        planet = prism(CrossSection([gear_profile(12, 1.0)]).rotate(math.degrees(a) + 15), -5, 5)
        planets.append(planet.translate((x, y, 0)))
        planets.append(cylinder(2.5, 4.9, 5.6, x=x, y=y))  # spacer between planet and plate
    plate = prism(circle(16.5) - circle(3.0), 5.3, 7.3)
    lightening = union(*[cylinder(2.2, 5, 9, x=9.5 * math.cos(a), y=9.5 * math.sin(a))
                         for a in np.radians([60, 180, 300])])
    shaft = cylinder(4, 7.3, 20) - prism(rect(10, 3, y=4 - 1), 14, 21)
    return union(*planets, plate - lightening, shaft)


def sun_gear() -> Manifold:
    """Spur sun gear, 12 teeth m=1, 10 mm face, D-bore for the 5 mm shaft; origin at its centre."""
    body = prism(CrossSection([gear_profile(12, 1.0)]), -5, 5) + cylinder(4.5, -7, -5)
    d_bore = circle(2.55) - rect(6, 3, y=2.55 + 1.5 - 0.5)
    return body - prism(d_bore, -8, 6)


def reducer_cover() -> Manifold:
    """Round cover, 50 mm across, with an output-shaft bearing boss and four screw bosses; origin at its bottom."""
    disc = prism(circle(25), 0, 3) + cylinder(8, 3, 7) - cylinder(4.4, -1, 8)
    lip = prism(circle(16.8) - circle(15.5), -2, 0)  # centres on the ring's tooth tips
    body = disc + lip
    for k in range(4):
        a = math.pi / 4 + k * math.pi / 2
        x, y = 21 * math.cos(a), 21 * math.sin(a)
        body = body - cylinder(1.6, -1, 4, x=x, y=y)
    body = body + prism(rect(10, 2, x=0, y=16), 3, 4.5)  # an arrow-like rib that marks the front
    return body


def along_x(m: Manifold) -> Manifold:
    """A solid built along z, turned to lie along x."""
    return m.rotate((0, 90, 0))


def tin_box() -> Manifold:
    """A lidded tin 150 x 100 x 55 mm, origin at the bottom centre: the lid 3 mm wider over the top 15 mm, a
    hinge on the back, a clasp in front. A half turn about z maps it onto itself but for the hinge and clasp."""
    body = prism(rounded_rect(150, 100, 12), 0, 42) + prism(rounded_rect(153, 103, 13.5), 40, 55)
    for x in (-40.0, 40.0):
        body = body + along_x(Manifold.cylinder(30, 3.5, 3.5, SEGMENTS, True)).translate((x, 52.5, 44))
    return body + prism(rect(22, 4, y=-53.5), 36, 50)


def watering_can() -> Manifold:
    """A watering can, origin at the bottom centre: a 100 mm body 120 mm tall with a rim, a spout rising to
    the front, a handle arching over the back."""
    body = cylinder(50, 0, 120) + cylinder(40, 120, 126) - cylinder(36, 100, 130)
    spout = Manifold.cylinder(125, 9, 5, SEGMENTS).rotate((0, 50, 0)).translate((30, 0, 20))
    rose = Manifold.cylinder(10, 10, 10, SEGMENTS).rotate((0, 50, 0)).translate((30 + 125 * math.sin(math.radians(50)),
                                                                                  0, 20 + 125 * math.cos(math.radians(50))))
    ring = prism(circle(42) - circle(33), -7, 7).rotate((90, 0, 0)).translate((-35, 0, 95))
    handle = ring - Manifold.cube((200, 40, 200), True).translate((65, 0, 95))  # the arch outside the body
    return union(body, spout, rose, handle)


def hole_punch() -> Manifold:
    """A two-hole punch 140 x 60 x 58 mm, origin at the bottom centre: a base plate, two punch towers, a flat
    lever, a finger grip on one end of the plate only: a half turn about z nearly maps it onto itself."""
    plate = prism(rounded_rect(130, 60, 6), 0, 10)
    towers = union(*(cylinder(13, 10, 42, x=x) for x in (-40.0, 40.0)))
    lever = prism(rounded_rect(140, 48, 8), 42, 52) + prism(rect(60, 20), 52, 58)
    grip = prism(rect(12, 30, x=71), 0, 8)
    return union(plate, towers, lever, grip)


def toy_duck() -> Manifold:
    """A toy duck about 105 x 60 x 78 mm, origin under its body: an egg body flattened underneath, a head,
    a beak and a tail."""
    body = Manifold.sphere(1, SEGMENTS).scale((45, 30, 26)).translate((0, 0, 26))
    head = Manifold.sphere(17, SEGMENTS).translate((28, 0, 58))
    beak = along_x(Manifold.cylinder(16, 7, 2.5, SEGMENTS)).translate((42, 0, 56))
    tail = Manifold.cylinder(16, 9, 2, SEGMENTS).rotate((0, -60, 0)).translate((-38, 0, 34))
    duck = union(body, head, beak, tail)
    return duck - Manifold.cube((200, 200, 100), True).translate((0, 0, -47))  # flat underneath at z = 3


def label() -> Manifold:
    """A 60 x 40 x 3 mm label plate with a notch on one short side (so its turn is seen)."""
    return prism(rounded_rect(60, 40, 3) - rect(8, 12, x=30), 0, 3)


ENGINE_SEATS = [(x, y) for y in (35.0, -35.0) for x in (-120.0, -40.0, 40.0, 120.0)]  # seat centres on the head, mm
SEAT_TOP = 100.0  # the seats' pads rise from the head's deck (z = 90) to here
SEAT_POST = (10.0, 6.0)  # each seat's post, off the pad's centre (so a seat's turn is seen), mm


def engine_head() -> Manifold:
    """An engine-like cylinder head 320 x 140 x 90 mm, origin at the bottom centre: a block with a rail round
    the deck and eight rocker-arm seats on it (ENGINE_SEATS), each a pad 44 x 34 x 10 mm with a post (10 mm
    across, 14 mm tall) off its centre and an oil hole, and ribs and bolt bosses on the sides."""
    block = prism(rounded_rect(320, 140, 6), 0, 90)
    rail = prism(rect(320, 140) - rect(308, 128), 90, 96)
    ribs = [prism(rect(6, 150), 10, 80).translate((x, 0, 0)) for x in (-150.0, -80.0, 0.0, 80.0, 150.0)]
    bosses = [cylinder(7.0, 0, 90, x, y) for x in (-155.0, 155.0) for y in (-66.0, 66.0)]
    seats = []
    for x, y in ENGINE_SEATS:
        pad = prism(rounded_rect(44, 34, 3), 90, SEAT_TOP).translate((x, y, 0))
        post = cylinder(5.0, SEAT_TOP, SEAT_TOP + 14.0, x + SEAT_POST[0], y + SEAT_POST[1])
        seats.append(union(pad, post) - cylinder(3.0, SEAT_TOP - 6.0, SEAT_TOP + 1.0, x - 12.0, y))
    return union(block, rail, *ribs, *bosses, *seats)


def rocker_arm() -> Manifold:
    """A rocker arm 62 x 14 x 9 mm, origin at its pivot bore's centre on its underside: the bore (10.6 mm)
    at one end, a pad at the other, a rib along its top."""
    body = prism(rounded_rect(62, 14, 6), 0, 9).translate((24.0, 0, 0))
    rib = prism(rect(40, 5), 9, 13).translate((26.0, 0, 0))
    tip = prism(rounded_rect(10, 14, 3), -4, 0).translate((50.0, 0, 0))
    return union(body, rib, tip) - cylinder(5.3, -1.0, 14.0)


# ----------------------------------------------------------------------------------- writing


def to_trimesh(m: Manifold) -> trimesh.Trimesh:
    mesh = m.to_mesh()
    tm = trimesh.Trimesh(np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts), process=False)
    if not tm.is_watertight:
        raise RuntimeError("generated mesh is not watertight")
    return tm


def write_mesh(m: Manifold, path: Path) -> None:
    tm = to_trimesh(m)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = tm.export(file_type=path.suffix[1:])
    path.write_bytes(data if isinstance(data, bytes) else data.encode())


HELICAL_YAML = """\
# Helical gearbox sample assembly, generated by sample_assemblies/generate.py (do not edit by hand).
format: apose-assembly/1
name: helical_gearbox
units: mm                 # the meshes are in millimetres
parts:
  casing:
    mesh: casing.stl
    color: [0.55, 0.58, 0.62]
  pinion:                 # 14 teeth, m=2, 15 deg helix, keyed bore: no symmetry
    mesh: pinion.stl
    color: [0.90, 0.62, 0.0]
  wheel:                  # 22 teeth, plain bore: 22-fold symmetric about its axis
    mesh: wheel.stl
    color: [0.34, 0.71, 0.91]
    symmetry: {axis: [0, 0, 1], order: 22}
  lid:
    mesh: lid.obj
    color: [0.0, 0.62, 0.45]
steps:
  - part: pinion
    base: [casing]
    pose_in_base:
      translation: [-20.0, 0.0, 14.5]
      rotation: {quat_wxyz: [1, 0, 0, 0]}
  - part: wheel
    base: [casing, pinion]
    pose_in_base:
      translation: [16.0, 0.0, 14.5]
      rotation: {euler_deg: [0, 0, 8.1818], order: xyz}   # half a tooth, so the teeth mesh
  - part: lid
    base: [casing, pinion, wheel]
    pose_in_base:
      translation: [0.0, 0.0, 24.0]
camera:
  width: 640
  height: 480
  fx: 615.0
  fy: 615.0
  cx: 320.0
  cy: 240.0
"""

PLANETARY_YAML = """\
# Planetary reducer sample assembly, generated by sample_assemblies/generate.py (do not edit by hand).
format: apose-assembly/1
name: planetary_reducer
units: mm
parts:
  motor:
    mesh: motor.ply
    color: [0.25, 0.25, 0.28]
  sun_gear:               # hidden inside the ring housing once that is on: occluded in later steps
    mesh: sun_gear.ply
    color: [0.90, 0.62, 0.0]
    grasps:               # T_part_gripper: the TCP's z points into the part, y is the jaws' closing direction
      - name: teeth       # from above, the jaws on the tooth tips (14 mm across) at mid-face
        pose_in_part: {translation: [0, 0, 0], rotation: {euler_deg: [180, 0, 0], order: xyz}}
        width: 14
  housing:                # square flange, four ribs, 36-tooth ring: a quarter turn maps it onto itself
    mesh: housing.ply
    color: [0.55, 0.58, 0.62]
    symmetry: {axis: [0, 0, 1], order: 4}
    grasps:
      - name: ring        # from above, across the ring (50 mm) between two ribs
        pose_in_part: {translation: [0, 0, 13], rotation: {euler_deg: [180, 0, 45], order: xyz}}
        width: 50
  carrier:                # planet carrier with its three planets, one rigid part
    mesh: carrier.ply
    color: [0.34, 0.71, 0.91]
    grasps:
      - name: shaft       # from above, on the 8 mm output shaft
        pose_in_part: {translation: [0, 0, 16], rotation: {euler_deg: [180, 0, 0], order: xyz}}
        width: 8
  cover:
    mesh: cover.stl
    color: [0.0, 0.62, 0.45]
    grasps:
      - name: boss        # from above, on the 16 mm bearing boss
        pose_in_part: {translation: [0, 0, 5.5], rotation: {euler_deg: [180, 0, 0], order: xyz}}
        width: 16
      - name: rim         # across the whole cover (50 mm), turned a quarter
        pose_in_part: {translation: [0, 0, 1.5], rotation: {euler_deg: [180, 0, 90], order: xyz}}
        width: 50
gripper:                  # a parallel-jaw gripper, for the width checks and for drawing
  type: parallel
  max_width: 80
  finger_length: 45
steps:
  - part: sun_gear
    base: [motor]
    mates:                 # the pose as a CAD engineer gives it; the loader solves it (and checks pose_in_base)
      - type: coaxial      # the D-bore on the 5 mm shaft
        base: {point: [0, 0, 42], direction: [0, 0, 1]}
        part: {point: [0, 0, 0], direction: [0, 0, 1]}
      - type: contact      # the hub's underside 3 mm above the motor's boss
        base: {point: [0, 0, 42], normal: [0, 0, 1]}
        part: {point: [0, 0, -7], normal: [0, 0, -1]}
        offset: 3
      - type: contact      # the bore's flat facing the shaft's flat, 0.05 mm clearance: sets the turn
        base: {point: [0, 2.0, 52], normal: [0, 1, 0]}
        part: {point: [0, 2.05, 0], normal: [0, -1, 0]}
        offset: 0.05
    pose_in_base:
      translation: [0.0, 0.0, 52.0]
    approach: {direction: [0, 0, -1], distance: 30}   # slid down the shaft from 30 mm above
  - part: housing
    base: [motor, sun_gear]
    pose_in_base:
      translation: [0.0, 0.0, 40.0]
    approach: {direction: [0, 0, -1], distance: 40}
  - part: carrier          # placed in the housing's frame; planets mesh inside the ring
    base: [housing, motor, sun_gear]
    pose_in_base:
      translation: [0.0, 0.0, 12.0]
      rotation: {euler_deg: [0, 0, 0], order: xyz}
    approach: {direction: [0, 0, -1], distance: 30}
  - part: cover
    base: [motor, sun_gear, housing, carrier]
    pose_in_base:
      translation: [0.0, 0.0, 62.0]
    approach: {direction: [0, 0, -1], distance: 25}
"""


DESK_YAML = """\
# Desk objects sample assembly, generated by sample_assemblies/generate.py (do not edit by hand).
# Household objects at their real size, each a root with a label to place on it, seen by a Kinect v1
# (LINEMOD's intrinsics): for benchmarks/captures.py's real-like rows (cluttered desks at 0.6-1.2 m).
format: apose-assembly/1
name: desk_objects
units: mm
parts:
  tin_box:                # a half turn nearly maps it onto itself (the hinge and the clasp differ)
    mesh: tin_box.stl
    color: [0.75, 0.2, 0.15]
  watering_can:
    mesh: watering_can.stl
    color: [0.2, 0.55, 0.3]
  hole_punch:             # a half turn nearly maps it onto itself (the grip on one end)
    mesh: hole_punch.stl
    color: [0.3, 0.3, 0.35]
  toy_duck:
    mesh: toy_duck.stl
    color: [0.95, 0.8, 0.1]
  label_tin:
    mesh: label.stl
    color: [0.95, 0.95, 0.9]
  label_can:
    mesh: label.stl
    color: [0.95, 0.95, 0.9]
  label_punch:
    mesh: label.stl
    color: [0.95, 0.95, 0.9]
  label_duck:
    mesh: label.stl
    color: [0.95, 0.95, 0.9]
steps:
  - part: label_tin       # on the lid, towards the clasp
    base: [tin_box]
    pose_in_base:
      translation: [30.0, -15.0, 55.0]
  - part: label_can       # on the body's side, facing the spout
    base: [watering_can]
    pose_in_base:
      translation: [50.0, 0.0, 60.0]
      rotation: {euler_deg: [0, 90, 0], order: xyz}
  - part: label_punch     # on the lever's top, its notch towards the grip
    base: [hole_punch]
    pose_in_base:
      translation: [0.0, 0.0, 58.0]
  - part: label_duck      # on its back
    base: [toy_duck]
    pose_in_base:
      translation: [-12.0, 0.0, 52.0]
      rotation: {euler_deg: [0, -10, 0], order: xyz}
camera:                   # Kinect v1 as in LINEMOD
  width: 640
  height: 480
  fx: 572.4114
  fy: 573.57043
  cx: 325.2611
  cy: 242.04899
"""


def engine_yaml() -> str:
    """The engine sample's file: eight seats, each a region (`roi`) of the one head mesh and its own root, and an
    arm placed on each seat's post."""
    lines = ["# Engine head sample assembly, generated by sample_assemblies/generate.py (do not edit by hand).",
             "# Eight rocker-arm seats, each a region of interest (roi) of one engine-head mesh and its own root",
             "# (the paper's use case), and a rocker arm to place on each seat's post. benchmarks/seats.py renders",
             "# it seen from 0.45-0.8 m, as an eye-in-hand camera sees it (apose render frames it from farther).",
             "format: apose-assembly/1", "name: engine_head", "units: mm", "parts:"]
    for k, (x, y) in enumerate(ENGINE_SEATS, 1):
        lines += [f"  seat_{k}:", "    mesh: engine_head.stl", "    color: [0.62, 0.64, 0.66]",
                  f"    roi: {{box: {{center: [{x:g}, {y:g}, {SEAT_TOP - 2:g}], size: [64, 50, 40]}}}}"]
    for k in range(1, len(ENGINE_SEATS) + 1):
        lines += [f"  arm_{k}:", "    mesh: rocker_arm.stl", "    color: [0.85, 0.55, 0.15]"]
    lines.append("steps:")
    for k, (x, y) in enumerate(ENGINE_SEATS, 1):
        turn = 0 if y > 0 else 180  # the arms point away from the head's middle
        lines += [f"  - part: arm_{k}", f"    base: [seat_{k}]", "    pose_in_base:",
                  f"      translation: [{x + SEAT_POST[0]:g}, {y + SEAT_POST[1]:g}, {SEAT_TOP + 3:g}]",
                  f"      rotation: {{euler_deg: [0, 0, {turn + 90}], order: xyz}}",
                  "    approach: {direction: [0, 0, -1], distance: 30}"]
    lines += ["camera:                   # an eye-in-hand RealSense-like camera", "  width: 640", "  height: 480",
              "  fx: 615.0", "  fy: 615.0", "  cx: 320.0", "  cy: 240.0"]
    return "\n".join(lines) + "\n"


def generate(out: Path) -> list[Path]:
    """Write the sample assemblies under `out`; returns the assembly files."""
    hg, pr = out / "helical_gearbox", out / "planetary_reducer"
    write_mesh(gearbox_casing(), hg / "casing.stl")
    write_mesh(helical_gear(14, 2.0, 12.0, 15.0, 4.0, 7.0, keyway=True), hg / "pinion.stl")
    write_mesh(helical_gear(22, 2.0, 12.0, -15.0, 4.0, 8.5, keyway=False), hg / "wheel.stl")
    write_mesh(gearbox_lid(), hg / "lid.obj")
    (hg / "assembly.yaml").write_text(HELICAL_YAML)
    write_mesh(motor_block(), pr / "motor.ply")
    write_mesh(sun_gear(), pr / "sun_gear.ply")
    write_mesh(ring_housing(), pr / "housing.ply")
    write_mesh(planet_carrier(), pr / "carrier.ply")
    write_mesh(reducer_cover(), pr / "cover.stl")
    (pr / "assembly.yaml").write_text(PLANETARY_YAML)
    dk = out / "desk_objects"
    write_mesh(tin_box(), dk / "tin_box.stl")
    write_mesh(watering_can(), dk / "watering_can.stl")
    write_mesh(hole_punch(), dk / "hole_punch.stl")
    write_mesh(toy_duck(), dk / "toy_duck.stl")
    write_mesh(label(), dk / "label.stl")
    (dk / "assembly.yaml").write_text(DESK_YAML)
    en = out / "engine_head"
    write_mesh(engine_head(), en / "engine_head.stl")
    write_mesh(rocker_arm(), en / "rocker_arm.stl")
    (en / "assembly.yaml").write_text(engine_yaml())
    step_files = _make_step().generate(out)  # the STEP sample: its B-rep written by hand
    return [hg / "assembly.yaml", pr / "assembly.yaml", dk / "assembly.yaml", en / "assembly.yaml", step_files[-1]]


def _make_step():
    spec = importlib.util.spec_from_file_location("make_step", HERE / "make_step.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE, help="folder to write into (default: this folder)")
    args = ap.parse_args(argv)
    for f in generate(args.out):
        print(f"wrote {f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
