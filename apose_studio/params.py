"""The estimator's parameters, declared once.

`Params` is the schema: every field has its default (the `default` preset's value), its kind, its
range and a line saying what it does. Everything else is derived from it:

- an assembly file's `registration:` section (`check_overrides`: any field, by name, checked against
  its kind and range; an unknown key names the known ones);
- the CLI's `--preset`, `--upright` and `--param NAME=VALUE` (`parse_param`);
- the studio's preset list (`PRESETS`);
- the presets: `PRESETS` maps a name to the fields it overrides (data, not code).

`resolve_params(preset, file_section, **caller)` gives the Params a run uses: the preset, then the
file's section, then the caller's overrides. Lengths in metres.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import yaml

from apose_studio.errors import AposeError, Problem
from apose_studio.geometry.camera import CameraIntrinsics, camera_from_dict, fov_camera, is_number


def _p(default, kind: str, doc: str, lo=None, hi=None, choices: tuple = (), none: bool = False, unit: str = ""):
    """A field of the schema: `kind` bool | int | float | str | camera; `none`: None is allowed too;
    `unit` (m, s, voxel) says how its number reads."""
    meta = {"kind": kind, "doc": doc, "lo": lo, "hi": hi, "choices": choices, "none": none, "unit": unit}
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class Params:
    """One run's estimator settings (frozen: change one with `dataclasses.replace`)."""

    preset: str = _p("default", "str", "the preset these values start from", choices=("default", "paper"))
    # --- resolution and features
    voxel_size_m: float | None = _p(None, "float", "the fine voxel in metres; null: the base's diameter / "
                                    "voxels_per_diameter", 1e-4, 0.5, none=True, unit="m")
    voxels_per_diameter: float = _p(50.0, "float", "the scale-aware voxel: the base's diameter over this", 5, 500)
    normal_radius_factor: float = _p(2.5, "float", "normals' radius, x voxel", 0.5, 20, unit="voxel")
    feature_radius_factor: float = _p(5.0, "float", "FPFH radius, x voxel", 0.5, 50, unit="voxel")
    downsample: bool = _p(True, "bool", "FPFH on voxel-down-sampled clouds (ours) or on the full clouds (paper)")
    global_voxel_factor: float = _p(2.0, "float", "the global search works at voxel x this (coarser, faster)", 1, 10)
    # --- global registration
    global_source: str = _p("model", "str", "raycast: the paper's partial view of the CAD; model: the whole model "
                            "(no orientation needed)", choices=("model", "raycast"))
    source_camera: CameraIntrinsics | None = _p(None, "camera", "the virtual camera of the paper's ray cast "
                                                "(width, height, fx, fy, cx, cy); null: the real camera", none=True)
    ransac_max_iterations: int = _p(3000, "int", "RANSAC iterations", 1, 1_000_000)
    ransac_confidence: float = _p(0.999, "float", "RANSAC's stopping confidence", 1e-6, 1.0)
    ransac_edge_length: float = _p(0.9, "float", "RANSAC's edge-length check (similarity of matched edges)",
                                   1e-6, 0.999999)
    ransac_distance_factor: float = _p(1.5, "float", "RANSAC's inlier distance, x coarse voxel", 0.1, 20, unit="voxel")
    ransac_retry_iterations: int = _p(30000, "int", "when the fast RANSAC explains < 60 % of the target, retry this "
                                      "long (0: no retry)", 0, 1_000_000)
    mutual_filter: bool = _p(False, "bool", "keep only mutual nearest feature matches")
    feature_matches: int = _p(1, "int", "RANSAC draws from the k nearest model features of each target point", 1, 10)
    use_flips: bool = _p(True, "bool", "also start ICP from the global pose turned half round each principal axis")
    max_starts: int = _p(6, "int", "ICP from this many of the screened starting poses", 1, 64)
    retry_below: float = _p(0.95, "float", "retry RANSAC when the best start explains less than this share", 0, 1)
    upright: bool = _p(True, "bool", "where a table is seen, first search the yaw of the base standing on it as "
                       "modelled (CAD +z along the table's normal), then freely if that fits poorly")
    free_after_upright: bool = _p(True, "bool", "when the upright search's pose fits poorly, search freely too and "
                                  "keep the better (off for the mask's other readings: a reading that does not fit "
                                  "upright is the wrong reading)")
    # --- priors and symmetry
    use_orientation_prior: bool = _p(False, "bool", "with no prior from the caller, take the CAD's orientation as "
                                     "one (the paper does)")
    prior_fast_path: bool = _p(True, "bool", "with an orientation prior, try ICP from it first and stop if it fits")
    use_symmetries: bool = _p(True, "bool", "refine the symmetric twins of the best pose and report exact ones")
    # --- ICP and polish
    icp_threshold_factor: float = _p(0.6, "float", "ICP's correspondence distance, x voxel", 0.05, 20, unit="voxel")
    icp_max_iterations: int = _p(15, "int", "ICP iterations per start", 1, 1000)
    polish_voxel_factor: float = _p(0.5, "float", "> 0: a last ICP of the target (down-sampled at voxel x this) onto "
                                    "the model seen at the chosen pose, with the model's exact normals", 0, 10, unit="voxel")
    polish_threshold_factor: float = _p(1.0, "float", "the polish's correspondence distance, x voxel", 0.05, 20, unit="voxel")
    polish_min_step: float = _p(0.1, "float", "the polish stops once a step moves the base by less than this, x voxel "
                                "(0: only when its fit stops changing)", 0, 1, unit="voxel")
    # --- run control
    seed: int = _p(0, "int", "seeds every random choice: the same seed, the same answer", 0, 2 ** 32 - 1)
    deterministic: bool = _p(True, "bool", "numpy's seeded ICP and RANSAC (the same pose in any process) instead of "
                             "Open3D's multi-threaded ones")
    max_seconds: float = _p(0.0, "float", "a wall-clock limit for the searches (0: none, the default: the searches "
                            "are bounded by the counts above, so the same input gives the same answer however busy "
                            "the machine is); past it a search stops, says so, and the result is never confident",
                            0, 3600, unit="s")
    threads: int = _p(2, "int", "the mask's other readings after the first are estimated this many at a time (at "
                      "most the CPUs the process may use; 1: one after the other); the answer is the same on any "
                      "number", 1, 64)
    second_look: bool = _p(True, "bool", "a result that is not confident is estimated again on its mask cut to the "
                           "model's view at that pose, from its candidates (each refined on the cut, their twins and "
                           "neighbours compared there; no new search); kept only if that one is confident")
    second_look_from_pose: bool = _p(False, "bool", "the second look first refits from the pose it looks again at "
                                     "(ICP on the cut, kept where it is confident; the pose's own rivals were sought on "
                                     "the whole mask) and refines its candidates on the cut only where that fails; on for a region's part "
                                     "found whole (--instances all)")
    mask_hypotheses: bool = _p(True, "bool", "a result that is not confident is estimated again on other readings of "
                               "the mask (without what lies on the base or stands in front of it); the one whose model "
                               "explains the frame best is kept")
    settle: bool = _p(True, "bool", "a result that is not confident and that the depth contradicts (the camera sees "
                      "past the model) is refitted without the depth lying in front of the model's surface (a plate "
                      "lying on the base tilts the fit towards itself); kept when it explains the frame better (a whole base, "
                      "not a region of a larger part)")
    scale_check: bool = _p(True, "bool", "a confident result is refitted with the depth scaled 12 % either way about "
                           "the camera; where the model explains a scaled depth clearly better, the depth_scale or the "
                           "intrinsics are off and the result is not confident (registration.calibration)")
    colour_check: bool = _p(True, "bool", "after the estimate, compare the depth's edges with the colour image's around "
                            "the object, less the edges the object's own shape makes at its pose (creases, rims); a clear "
                            "shift found there (a Kinect v1's or Xtion's depth is often registered a few pixels off) "
                            "counts against the confidence, by how far it would put the pose off")
    move_depth_to_colour: bool = _p(True, "bool", "when the colour check finds the depth clearly off the colour image, "
                                    "move the depth back by that shift and estimate again; that estimate is the "
                                    "result when no shift is left after it (else the first, not confident)")
    # --- tracking (registration.track: a frame's pose from the frame before's)
    track_motion: float = _p(0.15, "float", "tracking follows the base this far between frames, x its diameter (the "
                             "depth searched around its last pose)", 0.01, 1.0)
    track_points: int = _p(2000, "int", "depth points a tracked frame registers (its polish: all of them; its rough fit: "
                           "a few hundred)", 50, 100_000)
    track_iterations: int = _p(12, "int", "ICP iterations a tracked frame may take in all", 1, 200)

    def voxel(self, diameter: float) -> float:
        return self.voxel_size_m if self.voxel_size_m else diameter / self.voxels_per_diameter


FIELDS: dict[str, dataclasses.Field] = {f.name: f for f in dataclasses.fields(Params)}

# name -> the fields it sets over Params' defaults
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},  # ours: scale-aware voxel, the whole model, upright yaw search, polish, second look
    # the authors' settings: voxel 8 mm, FPFH on the full clouds, RANSAC 100000 / 0.899, ICP at 0.4 voxel for
    # 30 iterations, the source ray-cast at 1280x720 with a 60 degree field of view, the CAD's orientation
    # trusted; Open3D's RANSAC and ICP, as they used (`deterministic: true` makes it repeatable)
    "paper": dict(preset="paper", voxel_size_m=0.008, voxels_per_diameter=40.0, normal_radius_factor=2.0,
                  feature_radius_factor=3.0, downsample=False, ransac_max_iterations=100000,
                  ransac_confidence=0.899, ransac_edge_length=0.09, ransac_distance_factor=1.2,
                  icp_threshold_factor=0.4, icp_max_iterations=30, global_source="raycast",
                  source_camera=fov_camera(1280, 720, 60.0), use_symmetries=False, use_orientation_prior=True,
                  deterministic=False, global_voxel_factor=1.0, ransac_retry_iterations=0, use_flips=False,
                  prior_fast_path=False, upright=False, polish_voxel_factor=0.0, max_seconds=0.0, second_look=False,
                  mask_hypotheses=False, settle=False, colour_check=False,
                  move_depth_to_colour=False, scale_check=False),
}
PRESET_PARAMS: dict[str, Params] = {name: Params(**over) for name, over in PRESETS.items()}


def expected(name: str) -> str:
    """What a field takes, in words (for error messages and docs)."""
    m = FIELDS[name].metadata
    kind, lo, hi = m["kind"], m["lo"], m["hi"]
    if m["choices"]:
        text = "one of " + ", ".join(m["choices"])
    elif kind == "bool":
        text = "true or false"
    elif kind == "camera":
        text = "a mapping with width, height, fx, fy, cx, cy"
    elif kind == "int":
        text = f"a whole number from {lo} to {hi}"
    elif m["unit"] == "m":
        text = f"a length in metres from {lo:g} to {hi:g}"
    elif m["unit"] == "s":
        text = f"seconds from {lo:g} (no limit) to {hi:g}"
    else:
        text = f"a number from {lo:g} to {hi:g}" + (" (x voxel)" if m["unit"] == "voxel" else "")
    return text + (" (or null)" if m["none"] else "")


def check_value(name: str, v, file: str, key: str) -> tuple[Any, list[Problem]]:
    """One field's value checked against the schema: (the value as Params holds it, problems)."""
    m = FIELDS[name].metadata
    if v is None and m["none"]:
        return None, []
    kind = m["kind"]
    if kind == "camera":
        if isinstance(v, CameraIntrinsics):
            return v, []
        cam, problems = camera_from_dict(v, file, key)
        return cam, problems
    ok = {"str": lambda: isinstance(v, str), "bool": lambda: isinstance(v, bool),
          "int": lambda: isinstance(v, int) and not isinstance(v, bool), "float": lambda: is_number(v)}[kind]()
    if ok and m["choices"]:
        ok = v in m["choices"]
    elif ok and kind in ("int", "float"):
        ok = m["lo"] <= v <= m["hi"]
    if not ok:
        return None, [Problem(file, key, f"expected {expected(name)}, got {v!r}")]
    return (float(v) if kind == "float" else v), []


def check_overrides(data, file: str, key: str = "registration") -> tuple[dict[str, Any], list[Problem]]:
    """An assembly file's `registration` section (or any mapping of overrides) checked against the schema:
    (the accepted values by name, every problem with its key path)."""
    if data is None:
        return {}, []
    if not isinstance(data, Mapping):
        return {}, [Problem(file, key, f"expected a mapping of parameter names, got {type(data).__name__}")]
    values, problems = {}, []
    for name, v in data.items():
        where = f"{key}.{name}"
        if name not in FIELDS:
            problems.append(Problem(file, where, f"unknown parameter; known: {', '.join(FIELDS)}"))
            continue
        value, found = check_value(name, v, file, where)
        if found:
            problems += found
        else:
            values[name] = value
    return values, problems


class RegistrationConfig(Mapping):
    """An assembly file's `registration` section: checked overrides of Params' fields, by name (read-only)."""

    def __init__(self, **values):
        checked, problems = check_overrides(values, "registration", "registration")
        if problems:
            raise AposeError("; ".join(str(p) for p in problems))
        self._values = checked

    @classmethod
    def _checked(cls, values: dict) -> "RegistrationConfig":
        """One from values check_overrides already accepted (not checked again)."""
        out = cls.__new__(cls)
        out._values = dict(values)
        return out

    def __getitem__(self, name):
        return self._values[name]

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"RegistrationConfig({', '.join(f'{k}={v!r}' for k, v in self._values.items())})"

    def overrides(self) -> dict[str, Any]:
        return dict(self._values)


def registration_from_dict(data, file: str, key: str = "registration") -> tuple[RegistrationConfig, list[Problem]]:
    values, problems = check_overrides(data, file, key)
    return RegistrationConfig._checked(values), problems


def registration_to_dict(reg: RegistrationConfig) -> dict:
    """The section as written back to a file (a camera as its mapping)."""
    return {k: (dataclasses.asdict(v) if isinstance(v, CameraIntrinsics) else v) for k, v in reg.items()}


def parse_param(text: str) -> tuple[str, Any]:
    """`--param NAME=VALUE` -> (name, value) checked against the schema (VALUE read as YAML: 0.004, true,
    null). AposeError naming the flag and what the field takes."""
    name, sep, raw = text.partition("=")
    name = name.strip()
    if not sep or name not in FIELDS:
        raise AposeError(f"--param {text}: expected NAME=VALUE with NAME one of {', '.join(FIELDS)}")
    try:
        v = yaml.safe_load(raw) if raw.strip() else None
    except (yaml.YAMLError, ValueError):  # ValueError: an integer of more digits than Python converts
        v = raw
    value, problems = check_value(name, v, "--param", name)
    if problems:
        raise AposeError(f"--param {name}: expected {expected(name)}, got {raw!r}")
    return name, value


def resolve_params(preset: str = "default", config: Mapping | None = None, **overrides) -> Params:
    """The preset's parameters, overridden by the assembly file's `registration` section and then by the
    caller. Every override is checked against the schema (AposeError naming it)."""
    cfg = dict(config) if config else {}
    preset = overrides.pop("preset", None) or cfg.pop("preset", None) or preset
    cfg.pop("preset", None)
    if preset not in PRESETS:
        raise AposeError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    checked, problems = check_overrides(overrides, "parameters", "")
    if problems:
        raise AposeError("; ".join(f"{p.key.lstrip('.')}: {p.what}" for p in problems))
    return dataclasses.replace(PRESET_PARAMS[preset], **{**cfg, **checked})


def _shown(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, CameraIntrinsics):
        return f"{v.width}x{v.height}, f {v.fx:.1f} px"
    if isinstance(v, bool):
        return str(v).lower()
    return f"{v:g}" if isinstance(v, float) else str(v)


def parameter_table() -> str:
    """Every parameter as a Markdown table (name, default, paper, what it takes, what it does): the
    reference in docs/ASSEMBLY_FILES.md is this table (tests/test_params.py checks they agree)."""
    rows = ["| name | default | paper | takes | what it does |", "|---|---|---|---|---|"]
    paper = PRESET_PARAMS["paper"]
    for name, f in FIELDS.items():
        if name != "preset":
            rows.append(f"| `{name}` | {_shown(f.default)} | {_shown(getattr(paper, name))} | {expected(name)} | "
                        f"{f.metadata['doc']} |")
    return "\n".join(rows)
