"""Architecture counts on a source tree: run on this checkout or an old one.

    python bench/arch_counts.py [ROOT]     # ROOT: a checkout of the repository (default: this one)

Counts, over the project packages (tests and bench left out):

* ``validators``: places outside ``core/config.py`` that compute a mapping's unknown keys themselves
  (``set(a) - set(b)``, ``set(a).difference(b)``, ``a.keys() - b``) instead of calling the core loader;
* ``progress_shapes``: distinct shapes of the calls ``progress(...)`` / ``progress_cb(...)`` / ``on_progress``
  make (positional argument count, keyword names), and ``progress_calls_off_protocol``: calls that are not
  the core protocol's ``progress(task, done, total)``;
* ``progress_aliases``: module-level ``Progress = Callable[...]`` aliases other than core's protocol;
* ``exception_classes`` and ``exceptions_without_base``: classes deriving (in the project) from a builtin
  exception, and those of them that do not derive from ``RoomcapError``;
* ``raise_valueerror``: ``raise ValueError(...)`` statements;
* ``systemexit_str``: ``raise SystemExit(<text>)`` / ``sys.exit(<text>)``; ``scripts_unguarded``: console
  scripts whose ``main`` is not wrapped by ``core.cli.guarded``;
* ``function_imports``: project imports inside functions (``lazy_heavy``: imports of torch, onnxruntime,
  depthai, bpy or opensim inside functions, the allowed lazy loads);
* ``import_cycles``: strongly connected components (size > 1) of the module import graph, function-level
  imports included (grimp), and ``imports_against_order``: import edges from a lower layer to a higher one;
* ``long_positional``: public functions with 8 or more parameters that can be passed positionally;
* ``private_imports``: ``from <package> import _name`` where the package is another top-level project
  package than the importing module's (a private name used across a package boundary);
* ``long_functions``: functions (methods included) over 80 lines, and ``largest_module``: the longest module
  in lines;
* ``option_reads``: per stage option name (``chunk_s``, ``workers``, ``executor``, ``tracker``, ``preset``),
  the places that read it from a mapping (``x.get("name"...)`` or ``x["name"]``); ``option_parses``: per
  option, the modules that parse it: those reads, the config fields that declare it (a class body's
  ``name: type``) and calls of a parser named for it (``parse_chunk_s(...)``), counted once per module;
  ``option_compares``: comparisons of an attribute of that name with a string (``cfg.tracker == "greedy"``:
  string dispatch, or a check of the value); ``preset_lookups``: calls
  that resolve a keypoint preset's name (``presets()``, ``preset_config(...)``);
* ``kind_dispatch``: lines of ``forecast/`` outside the model registry (``forecast/registry.py``, now
  ``forecast/runtime/registry.py``) that compare a model's ``kind`` (a name ``kind``, an attribute ``.kind``,
  ``x["kind"]`` or ``x.get("kind")``) with a string or another model's ``.kind``;
  ``forecast_lines``: the lines of ``forecast/``'s modules in all and in its ``runtime`` and ``lab`` parts;
* ``doctested``: public functions and methods of ``core/``, ``calibrate/camera.py``, ``triangulate/`` and
  ``track/`` whose docstring holds a ``>>>`` example.
"""

from __future__ import annotations

import ast
import json
import re
import sys
import tomllib
from pathlib import Path

PACKAGES = [
    "core",
    "capture",
    "calibrate",
    "keypoints",
    "synthetic",
    "triangulate",
    "track",
    "outputs",
    "forecast",
    "pipeline",
]
ORDER = [
    "core",
    "capture",
    "calibrate",
    "keypoints",
    "synthetic",
    "triangulate",
    "track",
    "outputs",
    "forecast",
    "pipeline",
]
HEAVY = {"torch", "onnxruntime", "depthai", "bpy", "opensim", "mediapipe"}
BUILTIN_EXC = {n for n in dir(__builtins__) if isinstance(getattr(__builtins__, n, None), type)}
BUILTIN_EXC = {n for n in BUILTIN_EXC if issubclass(getattr(__builtins__, n), BaseException)}
PROGRESS_NAMES = {"progress", "progress_cb", "on_progress", "report_progress"}


def modules(root: Path):
    for pkg in PACKAGES:
        base = root / pkg
        if not base.is_dir():
            continue
        for f in sorted(base.rglob("*.py")):
            rel = f.relative_to(root).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join(parts), f


def _local(name: str) -> str:
    """A module name as this script names it: without the namespace (``roomcap.core.x`` is ``core.x``)."""
    return name.removeprefix("roomcap.")


def _name(node) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _is_set_call(node) -> bool:
    return isinstance(node, ast.Call) and _name(node.func) == "set"


def _is_keys(node) -> bool:
    return isinstance(node, ast.Call) and _name(node.func) == "keys"


OPTION_NAMES = ("chunk_s", "workers", "executor", "tracker", "preset")


def _option_key(node) -> str | None:
    """The string key of ``x.get("key", ...)`` or ``x["key"]``, else None."""
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "get"
        and node.args
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        return node.args[0].value
    if (
        isinstance(node, ast.Subscript)
        and isinstance(node.ctx, ast.Load)
        and isinstance(node.slice, ast.Constant)
        and isinstance(node.slice.value, str)
    ):
        return node.slice.value
    return None


def _module_of(place: str) -> str:
    """``pkg.mod`` of a place written ``pkg.mod:line ...`` or ``pkg.mod.Class:line ...``."""
    dotted = place.split(":")[0]
    head = dotted.rsplit(".", 1)
    return head[0] if len(head) == 2 and head[1][:1].isupper() else dotted


def count(root: Path) -> dict:
    res: dict = {
        "validators": [],
        "progress_shapes": set(),
        "progress_calls_off_protocol": 0,
        "progress_aliases": [],
        "raise_valueerror": 0,
        "systemexit_str": 0,
        "function_imports": 0,
        "lazy_heavy": 0,
        "long_positional": [],
        "private_imports": [],
        "long_functions": [],
        "doctested": 0,
    }
    option_reads: dict[str, list[str]] = {k: [] for k in OPTION_NAMES}
    option_parses: dict[str, list[str]] = {k: [] for k in OPTION_NAMES}
    preset_lookups: list[str] = []
    option_compares: list[str] = []
    largest = ("", 0)
    classes: dict[str, list[str]] = {}
    texts = {}
    for mod, f in modules(root):
        src = f.read_text()
        texts[mod] = src
        tree = ast.parse(src)
        n_lines = len(src.splitlines())
        if n_lines > largest[1]:
            largest = (mod, n_lines)
        doctest_scope = mod.split(".")[0] in ("core", "triangulate", "track") or mod == "calibrate.camera"
        parents = {}
        for node in ast.walk(tree):
            for ch in ast.iter_child_nodes(node):
                parents[ch] = node

        def in_function(n, parents=parents):
            p = parents.get(n)
            while p is not None:
                if isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    return True
                p = parents.get(p)
            return False

        for node in ast.walk(tree):
            if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub):
                if (
                    _is_set_call(node.left) and (_is_set_call(node.right) or isinstance(node.right, ast.Name))
                ) or (_is_keys(node.left)):
                    if mod != "core.config":
                        res["validators"].append(f"{mod}:{node.lineno}")
            if (
                isinstance(node, ast.Call)
                and _name(node.func) == "difference"
                and isinstance(node.func, ast.Attribute)
            ):
                if _is_set_call(node.func.value) and mod != "core.config":
                    res["validators"].append(f"{mod}:{node.lineno}")
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in PROGRESS_NAMES
            ):
                shape = (len(node.args), tuple(sorted(k.arg or "**" for k in node.keywords)))
                res["progress_shapes"].add(shape)
                if shape != (3, ()):
                    res["progress_calls_off_protocol"] += 1
            if isinstance(node, ast.Assign) and any(_name(t) == "Progress" for t in node.targets):
                if mod != "core.progress":
                    res["progress_aliases"].append(mod)
            if (
                isinstance(node, ast.Raise)
                and isinstance(node.exc, ast.Call)
                and _name(node.exc.func) == "ValueError"
            ):
                res["raise_valueerror"] += 1
            if isinstance(node, ast.Call) and _name(node.func) in ("SystemExit", "exit") and node.args:
                a = node.args[0]
                if (isinstance(a, ast.Constant) and isinstance(a.value, str)) or isinstance(a, ast.JoinedStr):
                    res["systemexit_str"] += 1
            if isinstance(node, (ast.Import, ast.ImportFrom)) and in_function(node):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                names = [_local(n) for n in names]
                top = {n.split(".")[0] for n in names}
                if isinstance(node, ast.ImportFrom) and node.level:
                    top = {mod.split(".")[0]}
                if top & set(PACKAGES):
                    res["function_imports"] += 1
                if top & HEAVY:
                    res["lazy_heavy"] += 1
            if isinstance(node, ast.ClassDef):
                classes[node.name] = [_name(b) or "" for b in node.bases]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                pos = [a.arg for a in node.args.posonlyargs + node.args.args if a.arg not in ("self", "cls")]
                if len(pos) >= 8:
                    res["long_positional"].append(f"{mod}.{node.name}({len(pos)})")
                if doctest_scope and ">>>" in (ast.get_docstring(node) or ""):
                    res["doctested"] += 1
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno:
                length = node.end_lineno - node.lineno + 1
                if length > 80:
                    res["long_functions"].append(f"{mod}.{node.name} ({length})")
            if isinstance(node, ast.ImportFrom) and not node.level and node.module:
                other = _local(node.module).split(".")[0]
                if other in PACKAGES and other != mod.split(".")[0]:
                    for a in node.names:
                        if a.name.startswith("_") and not a.name.startswith("__"):
                            res["private_imports"].append(f"{mod} <- {node.module}.{a.name}")
            key = _option_key(node)
            if key in option_reads:
                option_reads[key].append(f"{mod}:{node.lineno}")
                option_parses[key].append(f"{mod}:{node.lineno} read")
            if isinstance(node, ast.ClassDef):
                for st in node.body:
                    if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name):
                        if st.target.id in option_parses:
                            option_parses[st.target.id].append(f"{mod}.{node.name}:{st.lineno} field")
            if isinstance(node, ast.Compare) and isinstance(node.left, ast.Attribute):
                consts = [
                    c for c in node.comparators if isinstance(c, ast.Constant) and isinstance(c.value, str)
                ]
                if node.left.attr in option_parses and consts:
                    option_compares.append(f"{node.left.attr}: {mod}:{node.lineno}")
            if isinstance(node, ast.Call):
                fname = _name(node.func) or ""
                for opt in option_parses:
                    if fname in (f"parse_{opt}", f"_parse_{opt}"):
                        option_parses[opt].append(f"{mod}:{node.lineno} {fname}()")
                if fname in ("presets", "preset_config"):
                    preset_lookups.append(f"{mod}:{node.lineno} {fname}()")

    def exc_root(name, seen=()):
        """'roomcap', 'builtin' or None (not an exception)."""
        if name == "RoomcapError":
            return "roomcap"
        if name in seen:
            return None
        out = None
        for b in classes.get(name, []):
            if b == "RoomcapError":
                return "roomcap"
            r = exc_root(b, (*seen, name)) if b in classes else ("builtin" if b in BUILTIN_EXC else None)
            if r == "roomcap":
                return "roomcap"
            out = out or r
        return out

    res["largest_module"] = f"{largest[0]} ({largest[1]})"
    res["option_reads"] = {k: len(v) for k, v in option_reads.items()}
    res["option_read_places"] = [f"{k}: {p}" for k, v in option_reads.items() for p in v]
    res["option_parses"] = {k: len({_module_of(p) for p in v}) for k, v in option_parses.items()}
    res["option_compares"] = option_compares
    res["option_parse_places"] = [f"{k}: {p}" for k, v in option_parses.items() for p in v]
    res["preset_lookups"] = preset_lookups

    excs = {c: exc_root(c) for c in classes if c != "RoomcapError"}
    excs = {c: r for c, r in excs.items() if r}
    res["exception_classes"] = len(excs)
    res["exceptions_without_base"] = sorted(c for c, r in excs.items() if r == "builtin")

    scripts = tomllib.loads((root / "pyproject.toml").read_text()).get("project", {}).get("scripts", {})
    unguarded = []
    for name, target in scripts.items():
        m, attr = target.split(":")
        m = _local(m)
        src = texts.get(m, "")
        if not re.search(rf"^{attr}\s*=\s*guarded\(", src, re.M):
            unguarded.append(name)
    res["scripts_unguarded"] = unguarded

    import grimp

    graph = grimp.build_graph("roomcap", include_external_packages=False)

    class _Local:  # the graph with this script's module names
        modules = {_local(m) for m in graph.modules if m != "roomcap"}

        @staticmethod
        def find_modules_directly_imported_by(v):
            imported = graph.find_modules_directly_imported_by("roomcap." + v)
            return {_local(w) for w in imported if w != "roomcap"}

    g = _Local
    mods = sorted(g.modules)
    # Tarjan's strongly connected components
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]
    sys.setrecursionlimit(10000)

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.find_modules_directly_imported_by(v):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                sccs.append(sorted(comp))

    for v in mods:
        if v not in index:
            strong(v)
    res["import_cycles"] = sccs
    against = []
    for v in mods:
        for w in g.find_modules_directly_imported_by(v):
            a, b = v.split(".")[0], w.split(".")[0]
            if a in ORDER and b in ORDER and ORDER.index(a) < ORDER.index(b):
                against.append(f"{v} -> {w}")
    res["imports_against_order"] = sorted(against)
    res["progress_shapes"] = sorted(str(s) for s in res["progress_shapes"])
    return res


def _mentions_kind(node) -> bool:
    if isinstance(node, ast.Name):
        return node.id == "kind"
    if isinstance(node, ast.Attribute):
        return node.attr == "kind"
    if isinstance(node, ast.Subscript):
        return isinstance(node.slice, ast.Constant) and node.slice.value == "kind"
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
        return bool(node.args) and isinstance(node.args[0], ast.Constant) and node.args[0].value == "kind"
    return False


def _is_name_text(node) -> bool:
    """A string, a tuple/list/set of strings, or another model's ``.kind``."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, str)
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return bool(node.elts) and all(
            isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts
        )
    return isinstance(node, ast.Attribute) and node.attr == "kind"


def forecast_counts(root: Path) -> dict:
    """``kind_dispatch`` places and ``forecast_lines`` (see the module docstring)."""
    places, lines = [], {"total": 0, "runtime": 0, "lab": 0, "modules": 0}
    for f in sorted((root / "forecast").rglob("*.py")):
        rel = f.relative_to(root).as_posix()
        src = f.read_text()
        n = len(src.splitlines())
        lines["total"] += n
        lines["modules"] += 1
        for part in ("runtime", "lab"):
            if rel.startswith(f"forecast/{part}/"):
                lines[part] += n
        if rel in ("forecast/registry.py", "forecast/runtime/registry.py"):
            continue
        seen = set()
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                if any(_mentions_kind(a) for a in sides) and any(_is_name_text(b) for b in sides):
                    if node.lineno not in seen:
                        seen.add(node.lineno)
                        places.append(f"{rel}:{node.lineno}")
    return {"kind_dispatch": places, "forecast_lines": lines}


def main() -> None:
    root = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parents[1]).resolve()
    r = count(root)
    r.update(forecast_counts(root))
    summary = {
        k: (len(v) if isinstance(v, list) else v)
        for k, v in r.items()
        if k not in ("progress_shapes", "option_read_places")
    }
    summary["progress_shapes"] = len(r["progress_shapes"])
    for k, v in r.items():
        if isinstance(v, list) and v:
            print(f"{k} ({len(v)}):")
            for x in v:
                print(f"  {x}")
    print("BENCH " + json.dumps({"root": str(root), **summary}))


if __name__ == "__main__":
    main()
