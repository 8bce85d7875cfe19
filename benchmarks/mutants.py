"""Mutation testing of the modules that decide answers: plant one small bug at a time, run the tests, count
the bugs they catch (killed) and those they miss (survived). No dependency beyond the standard library.

    .venv/bin/python benchmarks/mutants.py                       # every default module, its default tests
    .venv/bin/python benchmarks/mutants.py --modules apose_studio/geometry/metrics.py --tests tests/geometry/test_metrics.py
    .venv/bin/python benchmarks/mutants.py --modules apose_studio/registration/pipeline.py::judge --list

Each mutant is one edit found with `ast` (a comparison flipped, `and` for `or`, `+` for `-`, `max` for `min`
or `mean`, a number changed, a condition negated, a minus or a transpose dropped, a `return None`), written
into a COPY of the repository in a temporary folder: the real tree is never touched, so it is safe to run
while someone edits it (it tests the tree as it was when the run started). The tests run there with
`pytest -x -q` and a per-mutant timeout (a mutant that hangs counts as killed, marked "timeout"). Before
any mutant, the tests must pass on the unmutated copy, or the run stops.

A survivor is either a gap in the tests (write one that fails on it) or an equivalent mutant (no input can
tell it apart: say why). Not in CI: it takes minutes (one pytest run per mutant).

`path::name` restricts a module to one function or class (e.g. `pipeline.py::judge`). Text inside f-strings
and docstrings is not mutated (messages, not answers); neither are annotations, nor (unless --index-constants)
ints used as indices.
"""

from __future__ import annotations

import argparse
import ast
import copy
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

DEFAULT_MODULES = ["apose_studio/geometry/metrics.py", "apose_studio/geometry/se3.py", "apose_studio/assembly/mates.py",
                   "apose_studio/registration/types.py", "apose_studio/registration/pipeline.py::judge",
                   "apose_studio/studio/webguard.py", "apose_studio/data/outdir.py"]
# the tests that target each module directly (used when --tests is not given)
DEFAULT_TESTS = {
    "apose_studio/geometry/metrics.py": ["tests/geometry/test_metrics.py"],
    "apose_studio/geometry/se3.py": ["tests/geometry/test_se3.py"],
    "apose_studio/assembly/mates.py": ["tests/assembly/test_mates.py"],
    "apose_studio/registration/types.py": ["tests/registration/test_types.py"],
    "apose_studio/registration/pipeline.py": [  # judge()
        "tests/registration/test_pipeline.py::test_a_pose_the_camera_cannot_have_seen_is_not_ok",
        "tests/registration/test_pipeline.py::test_judge_edges_by_hand"],
    "apose_studio/studio/webguard.py": ["tests/studio/test_webguard.py"],
    "apose_studio/data/outdir.py": ["tests/data/test_outdir.py"],
}
IGNORE = (".git", ".venv", "__pycache__", ".pytest_cache", "artifacts", "out", "build", "*.egg-info", ".gl", ".whl",
          "*.pyc")

CMP_SWAPS = {ast.Lt: [ast.LtE, ast.Gt], ast.LtE: [ast.Lt, ast.GtE], ast.Gt: [ast.GtE, ast.Lt], ast.GtE: [ast.Gt, ast.LtE],
             ast.Eq: [ast.NotEq], ast.NotEq: [ast.Eq], ast.Is: [ast.IsNot], ast.IsNot: [ast.Is], ast.In: [ast.NotIn],
             ast.NotIn: [ast.In]}
BIN_SWAPS = {ast.Add: [ast.Sub], ast.Sub: [ast.Add], ast.Mult: [ast.Div], ast.Div: [ast.Mult], ast.FloorDiv: [ast.Div],
             ast.Pow: [ast.Mult], ast.Mod: [ast.Mult], ast.MatMult: [ast.Mult]}
CALL_SWAPS = {"max": ["min", "mean"], "min": ["max"], "mean": ["max", "median"], "median": ["mean"], "amax": ["amin"],
              "amin": ["amax"], "argmax": ["argmin"], "argmin": ["argmax"], "any": ["all"], "all": ["any"],
              "sum": ["mean"], "nanmax": ["nanmin"], "nanmin": ["nanmax"], "floor": ["ceil"], "ceil": ["floor"]}
SYMBOL = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=", ast.Is: "is",
          ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in", ast.Add: "+", ast.Sub: "-", ast.Mult: "*",
          ast.Div: "/", ast.FloorDiv: "//", ast.Pow: "**", ast.Mod: "%", ast.MatMult: "@", ast.And: "and", ast.Or: "or"}


@dataclass
class Mutant:
    module: str  # as given (path, or path::name)
    path: str  # repository-relative file
    line: int
    what: str  # the mutation, in words
    start: int  # byte span of the replaced source
    end: int
    text: str  # the replacement
    code: str = ""  # the original line, as it was when the run started

    @property
    def where(self) -> str:
        return f"{self.path}:{self.line}"


# ------------------------------------------------------------------------------------------------ finding


def _skipped_spans(tree: ast.AST) -> list[ast.AST]:
    """Nodes whose insides are not mutated: docstrings, f-strings, annotations, `from __future__`."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                out.append(first)
        if isinstance(node, ast.JoinedStr):
            out.append(node)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if node.returns is not None:
                out.append(node.returns)
            for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs:
                if a.annotation is not None:
                    out.append(a.annotation)
        if isinstance(node, ast.AnnAssign):
            out.append(node.annotation)
        if isinstance(node, ast.ImportFrom):
            out.append(node)
    return out


def _inside(node: ast.AST, spans: list[ast.AST]) -> bool:
    if not hasattr(node, "lineno"):
        return True
    a = (node.lineno, node.col_offset)
    b = (node.end_lineno, node.end_col_offset)
    return any((s.lineno, s.col_offset) <= a and b <= (s.end_lineno, s.end_col_offset) for s in spans)


def _number_variants(v) -> list:
    """Booleans flip; ints move by one; a float doubles and halves (a tolerance under 1e-4 becomes 0)."""
    if isinstance(v, bool):
        return [not v]
    if isinstance(v, int):
        return [1] if v == 0 else [v + 1, v - 1]
    if isinstance(v, float):
        if v == 0.0:
            return [1.0]
        return [0.0] if abs(v) < 1e-4 else [2 * v, v / 2]
    return []


def _is_index(node: ast.AST, parents: dict) -> bool:
    """An int used as a subscript or slice bound (T[:3, 3]): off-by-one there crashes or breaks everything."""
    p = parents.get(node)
    while p is not None and isinstance(p, (ast.Tuple, ast.Slice, ast.UnaryOp)):
        if isinstance(p, ast.Slice):
            return True
        node, p = p, parents.get(p)
    return isinstance(p, ast.Subscript) and p.slice is node


def _mutations(node: ast.AST, parents: dict, index_constants: bool = False) -> list[tuple[ast.AST, str, ast.AST | str]]:
    """(node to replace, the mutation in words, replacement node or source) for one node."""
    out = []
    if isinstance(node, ast.Compare):
        for i, op in enumerate(node.ops):
            for new in CMP_SWAPS.get(type(op), []):
                m = copy.deepcopy(node)
                m.ops[i] = new()
                out.append((node, f"{SYMBOL[type(op)]} -> {SYMBOL[new]}", m))
    elif isinstance(node, ast.BoolOp):
        new = ast.Or if isinstance(node.op, ast.And) else ast.And
        m = copy.deepcopy(node)
        m.op = new()
        out.append((node, f"{SYMBOL[type(node.op)]} -> {SYMBOL[new]}", m))
    elif isinstance(node, ast.BinOp):
        for new in BIN_SWAPS.get(type(node.op), []):
            m = copy.deepcopy(node)
            m.op = new()
            out.append((node, f"{SYMBOL[type(node.op)]} -> {SYMBOL[new]}", m))
    elif isinstance(node, ast.AugAssign):
        for new in BIN_SWAPS.get(type(node.op), []):
            m = copy.deepcopy(node)
            m.op = new()
            out.append((node, f"{SYMBOL[type(node.op)]}= -> {SYMBOL[new]}=", m))
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.Not)):
        if not (isinstance(node.op, ast.USub) and isinstance(node.operand, ast.Constant)):  # -1: a number, below
            out.append((node, "drop unary " + ("-" if isinstance(node.op, ast.USub) else "not"), node.operand))
    elif isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not (
            _is_index(node, parents) and isinstance(node.value, int) and not index_constants):
        parent = parents.get(node)
        neg = isinstance(parent, ast.UnaryOp) and isinstance(parent.op, ast.USub)
        target = parent if neg else node
        v = -node.value if neg else node.value
        for new in _number_variants(v):
            if isinstance(new, bool) or not (isinstance(new, (int, float)) and new < 0):
                rep = ast.Constant(new)
            else:
                rep = ast.UnaryOp(ast.USub(), ast.Constant(-new))
            out.append((target, f"{v!r} -> {new!r}", rep))
    elif isinstance(node, ast.Call):
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
        on_numpy = isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id in ("np", "numpy")
        for new in CALL_SWAPS.get(name, []):
            if new == "median" and not on_numpy:  # arrays have no .median(): a crash, not a bug worth a run
                continue
            m = copy.deepcopy(f)
            if isinstance(m, ast.Attribute):
                m.attr = new
            else:
                m.id = new
            out.append((f, f"{name}() -> {new}()", m))
        if isinstance(f, ast.Name) and f.id == "abs" and len(node.args) == 1:
            out.append((node, "drop abs()", node.args[0]))
    elif isinstance(node, ast.Attribute) and node.attr == "T" and isinstance(node.ctx, ast.Load):
        out.append((node, "drop .T (transpose)", node.value))
    elif isinstance(node, (ast.If, ast.While, ast.IfExp)):
        t = node.test
        if isinstance(t, ast.UnaryOp) and isinstance(t.op, ast.Not):
            pass  # the same as "drop unary not"
        elif isinstance(t, ast.Compare) and len(t.ops) == 1 and isinstance(t.ops[0], (ast.Eq, ast.NotEq, ast.Is, ast.IsNot,
                                                                                         ast.In, ast.NotIn)):
            pass  # the same as the comparison's own swap
        else:
            out.append((t, "negate the condition", ast.UnaryOp(ast.Not(), t)))
    elif isinstance(node, ast.Return) and node.value is not None and not (
            isinstance(node.value, ast.Constant) and node.value.value is None):
        out.append((node, "return None", "return None"))
    return out


def find_mutants(module: str, root: Path = REPO, index_constants: bool = False) -> list[Mutant]:
    path, _, name = module.partition("::")
    src = (root / path).read_bytes()
    tree = ast.parse(src)
    region = None
    if name:
        defs = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                and n.name == name]
        if not defs:
            raise SystemExit(f"error: {path} defines no function or class {name!r}")
        region = defs[0]
    line_starts = [0]
    for line in src.splitlines(keepends=True):
        line_starts.append(line_starts[-1] + len(line))
    parents = {c: p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}
    skip = _skipped_spans(tree)
    out, seen = [], set()
    for node in ast.walk(region if region is not None else tree):
        if not hasattr(node, "lineno") or _inside(node, skip):
            continue
        for target, what, rep in _mutations(node, parents, index_constants):
            start = line_starts[target.lineno - 1] + target.col_offset  # ast offsets are utf-8 bytes
            end = line_starts[target.end_lineno - 1] + target.end_col_offset
            text = rep if isinstance(rep, str) else ast.unparse(rep)
            if not isinstance(target, ast.stmt) and not isinstance(rep, str):
                text = f"({text})"
            key = (start, end, text)
            if key in seen:
                continue
            seen.add(key)
            code = src[line_starts[target.lineno - 1]:line_starts[target.lineno]].decode().strip()
            out.append(Mutant(module, path, target.lineno, what, start, end, text, code))
    out.sort(key=lambda m: (m.start, m.what))
    valid = []
    for m in out:  # a mutant must still be Python (a replacement in an odd spot may not be)
        try:
            ast.parse(apply(src, m))
        except SyntaxError:
            continue
        valid.append(m)
    return valid


def apply(src: bytes, m: Mutant) -> bytes:
    return src[:m.start] + m.text.encode() + src[m.end:]


# ------------------------------------------------------------------------------------------------ running


def make_copy(dest: Path) -> Path:
    shutil.copytree(REPO, dest, ignore=shutil.ignore_patterns(*IGNORE), symlinks=True)
    return dest


def env_for(copy_root: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(copy_root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONDONTWRITEBYTECODE"] = "1"  # a mutant of the same size written in the same second: no stale .pyc
    shared = Path(os.environ.get("APOSE_SHARED", REPO.parent / "shared"))
    if shared.is_dir():
        env["APOSE_SHARED"] = str(shared.resolve())  # the copy has no ../shared beside it
    env.pop("CI", None)
    return env


def run_tests(copy_root: Path, tests: list[str], timeout: float, python: str) -> tuple[str, float, str]:
    """('pass' | 'fail' | 'timeout', seconds, output tail)."""
    t = time.perf_counter()
    cmd = [python, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    try:
        r = subprocess.run(cmd, cwd=copy_root, env=env_for(copy_root), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - t, ""
    tail = (r.stdout + r.stderr)[-1500:]
    if r.returncode == 5 or "no tests ran" in tail:
        raise SystemExit(f"error: pytest collected no tests for {tests}:\n{tail}")
    return ("pass" if r.returncode == 0 else "fail"), time.perf_counter() - t, tail


def check_copy_imports_itself(copy_root: Path, python: str) -> None:
    r = subprocess.run([python, "-c", "import apose_studio; print(apose_studio.__file__)"], cwd=copy_root,
                       env=env_for(copy_root), capture_output=True, text=True)
    got = Path(r.stdout.strip() or "?").resolve()
    if copy_root.resolve() not in got.parents:
        raise SystemExit(f"error: in the copy, apose_studio is imported from {got}, not from the copy {copy_root}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Modules default to: " + ", ".join(DEFAULT_MODULES))
    ap.add_argument("--modules", nargs="+", default=DEFAULT_MODULES, metavar="PATH[::NAME]",
                    help="files to mutate, repository-relative; ::NAME limits one to a function or class")
    ap.add_argument("--tests", nargs="+", metavar="PYTEST_ARG",
                    help="the tests to run against every mutant (default: each module's own, see DEFAULT_TESTS)")
    ap.add_argument("--max-per-module", type=int, default=0, metavar="N",
                    help="at most N mutants per module, picked at random with --seed (default 0: all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the pick with --max-per-module (default 0)")
    ap.add_argument("--jobs", type=int, default=1, help="mutants tested at once, each in its own copy (default 1)")
    ap.add_argument("--timeout", type=float, default=0, metavar="S",
                    help="seconds per mutant before it counts as killed (timeout); default 0: 5 x the clean run + 30")
    ap.add_argument("--python", default=sys.executable, help="the interpreter that runs pytest (default: this one)")
    ap.add_argument("--index-constants", action="store_true",
                    help="also change ints used as indices (T[:3, 3]); off by default: they crash or break everything")
    ap.add_argument("--list", action="store_true", help="list the mutants and stop (runs nothing)")
    args = ap.parse_args(argv)

    plan: list[tuple[str, list[Mutant], list[str]]] = []
    for module in args.modules:
        path = module.partition("::")[0]
        if not (REPO / path).is_file():
            raise SystemExit(f"error: {path}: no such file in {REPO}")
        ms = find_mutants(module, index_constants=args.index_constants)
        if args.max_per_module and len(ms) > args.max_per_module:
            ms = sorted(random.Random(args.seed).sample(ms, args.max_per_module), key=lambda m: m.start)
        tests = args.tests or DEFAULT_TESTS.get(path)
        if not tests:
            raise SystemExit(f"error: no default tests for {path}; give --tests")
        plan.append((module, ms, tests))
    if args.list:
        for module, ms, tests in plan:
            print(f"{module}: {len(ms)} mutants; tests {' '.join(tests)}")
            for m in ms:
                print(f"  {m.where:<48} {m.what:<24} -> {m.text[:70]}")
        return 0

    tmp = Path(tempfile.mkdtemp(prefix="apose-mutants-"))
    try:
        copies = [make_copy(tmp / f"w{i}" / "main") for i in range(max(1, args.jobs))]
        check_copy_imports_itself(copies[0], args.python)
        pool: queue.Queue = queue.Queue()
        for c in copies:
            pool.put(c)
        lock = threading.Lock()
        rows, survivors = [], []
        for module, ms, tests in plan:
            status, secs, tail = run_tests(copies[0], tests, 1800, args.python)
            if status != "pass":
                print(f"error: the tests fail on the unmutated copy, so no mutant can be judged ({module}):\n{tail}")
                return 2
            timeout = args.timeout or 5 * secs + 30
            print(f"{module}: {len(ms)} mutants, tests {' '.join(tests)} ({secs:.1f} s clean, timeout {timeout:.0f} s)",
                  flush=True)
            results: dict[int, str] = {}

            def one(k: int, m: Mutant) -> None:
                root = pool.get()
                target = root / m.path
                original = target.read_bytes()
                try:
                    target.write_bytes(apply(original, m))
                    status, _, _ = run_tests(root, tests, timeout, args.python)
                finally:
                    target.write_bytes(original)
                    pool.put(root)
                results[k] = status
                with lock:
                    mark = {"pass": "SURVIVED", "fail": "killed", "timeout": "killed (timeout)"}[status]
                    print(f"  [{len(results):>3}/{len(ms)}] {m.where:<46} {m.what:<24} {mark}", flush=True)

            with ThreadPoolExecutor(max_workers=len(copies)) as ex:
                for f in [ex.submit(one, k, m) for k, m in enumerate(ms)]:
                    f.result()
            surv = [m for k, m in enumerate(ms) if results[k] == "pass"]
            timeouts = sum(s == "timeout" for s in results.values())
            rows.append((module, len(ms), len(ms) - len(surv), len(surv), timeouts))
            survivors += surv
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"\n{'module':<48} {'mutants':>7} {'killed':>7} {'survived':>8} {'timeouts':>8} {'score':>6}")
    for module, n, killed, surv, tmo in rows:
        print(f"{module:<48} {n:>7} {killed:>7} {surv:>8} {tmo:>8} {killed / n if n else 1:>6.0%}")
    tot = [sum(r[i] for r in rows) for i in (1, 2, 3, 4)]
    print(f"{'total':<48} {tot[0]:>7} {tot[1]:>7} {tot[2]:>8} {tot[3]:>8} {tot[1] / tot[0] if tot[0] else 1:>6.0%}")
    if survivors:
        print("\nsurvivors (a missing test, or an equivalent mutant to explain):")
        for m in survivors:
            print(f"  {m.where:<46} {m.what:<24} in: {m.code[:80]}")
    return 0


if __name__ == "__main__":
    if hasattr(signal, "SIGPIPE"):  # `... --list | head` ends quietly
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    sys.exit(main())
