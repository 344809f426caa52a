#!/usr/bin/env python3
"""Checks the workspace's layering (CI runs it from tools/scripts/test.sh).

1. Crate graph: every workspace crate has a layer, and depends (normal and build
   dependencies) only on crates of lower layers, or, for stages, on other stages:
       0 gprflow-params, gprflow-geometry, gprflow-msg
       1 gprflow-bus
       2 gprflow-stage
       3 gprflow-record
       4 gprflow-graph, gprflow-eval
       5 gprflow (the one-crate facade)
       6 stages/*            (never the facade, the graph/launcher, eval or tools)
       7 tools/*             (the simulator never a stage: it depends on messages only)
2. No stage crate, nor the runtime below the launcher, compiles zenoh (`cargo tree`).
3. Inside each crate, no circle of imports between its top-level modules (`crate::m`
   paths, and `super::m` in a top-level module's own file).

usage: tools/scripts/check-layers.py [--graph]   (--graph prints the crate graph)
"""
import json
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]

RUNTIME = {
    "gprflow-params": 0,
    "gprflow-geometry": 0,
    "gprflow-msg": 0,
    "gprflow-bus": 1,
    "gprflow-stage": 2,
    "gprflow-record": 3,
    "gprflow-graph": 4,
    "gprflow-eval": 4,
    "gprflow": 5,
}
STAGE, TOOL = 6, 7
# the crates that may reach zenoh: the launcher/bridge, the facade and the tools on top
ZENOH_ALLOWED = {"gprflow-graph", "gprflow", "gprflow-cli", "gprflow-bench", "gprflow-sim"}


def layer(pkg):
    if pkg["name"] in RUNTIME:
        return RUNTIME[pkg["name"]]
    rel = pathlib.Path(pkg["manifest_path"]).parent.relative_to(ROOT)
    if rel.parts[0] == "stages":
        return STAGE
    if rel.parts[0] == "tools":
        return TOOL
    sys.exit(f"{rel}: crate {pkg['name']} has no layer; add it to tools/scripts/check-layers.py")


def crate_graph(packages):
    names = {p["name"] for p in packages}
    edges = {}
    for p in packages:
        deps = {d["name"] for d in p["dependencies"] if d["name"] in names and d["kind"] in (None, "build")}
        edges[p["name"]] = sorted(deps)
    return edges


def check_crates(packages, edges):
    by_name = {p["name"]: p for p in packages}
    problems = []
    for name, deps in edges.items():
        mine = layer(by_name[name])
        is_sim = name == "gprflow-sim"
        for dep in deps:
            theirs = layer(by_name[dep])
            if mine == STAGE and theirs == STAGE:
                continue
            if mine == STAGE and dep in ("gprflow", "gprflow-graph", "gprflow-eval"):
                problems.append(f"stage {name} depends on {dep}: stages use messages and the stage SDK")
            elif is_sim and theirs == STAGE:
                problems.append(f"the simulator depends on stage {dep}: it may depend on messages only")
            elif theirs >= mine and not (mine == TOOL and theirs == TOOL):
                problems.append(f"{name} (layer {mine}) depends on {dep} (layer {theirs})")
    return problems


def check_zenoh(packages):
    problems = []
    for p in packages:
        if p["name"] in ZENOH_ALLOWED:
            continue
        tree = subprocess.run(
            ["cargo", "tree", "--offline", "-q", "-e", "normal", "-p", p["name"], "--prefix", "none"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        ).stdout
        if re.search(r"^zenoh v", tree, re.M):
            problems.append(f"{p['name']} compiles zenoh")
    return problems


USE = re.compile(r"\bcrate::([a-z_][a-z0-9_]*)")
SUPER = re.compile(r"\bsuper::([a-z_][a-z0-9_]*)")
TEST_MOD = re.compile(r"#\[cfg\(test\)\]\s*mod\s+\w+\s*\{", re.M)


def strip_tests(text):
    """Drops inline `#[cfg(test)] mod x { ... }` blocks (tests may use their parent)."""
    out, pos = [], 0
    for m in TEST_MOD.finditer(text):
        if m.start() < pos:
            continue
        out.append(text[pos:m.start()])
        depth, i = 1, m.end()
        while i < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[i], 0)
            i += 1
        pos = i
    out.append(text[pos:])
    return "".join(out)


def module_graph(src):
    """Top-level module -> the top-level modules its code names."""
    modules = {}
    for path in src.rglob("*.rs"):
        rel = path.relative_to(src)
        if rel.parts[0] in ("lib.rs", "main.rs", "bin"):
            continue
        if rel.name == "tests.rs" or "tests" in rel.parts[1:-1]:
            continue
        top = rel.parts[0].removesuffix(".rs")
        # comments (doc links included) are not imports
        text = re.sub(r"//.*", "", strip_tests(path.read_text()))
        refs = set(USE.findall(text))
        is_top_file = len(rel.parts) == 1 or (len(rel.parts) == 2 and rel.name == "mod.rs")
        if is_top_file:
            refs |= set(SUPER.findall(text))
        modules.setdefault(top, set()).update(refs)
    names = set(modules)
    return {m: sorted((refs & names) - {m}) for m, refs in modules.items()}


def cycles(graph):
    """Strongly connected components of more than one node (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, []):
            if w not in index:
                visit(w)
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
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def main():
    meta = json.loads(subprocess.run(
        ["cargo", "metadata", "--offline", "--format-version", "1", "--no-deps"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout)
    packages = meta["packages"]
    edges = crate_graph(packages)
    if "--graph" in sys.argv:
        for name in sorted(edges, key=lambda n: (layer(next(p for p in packages if p["name"] == n)), n)):
            print(f"{name} -> {', '.join(edges[name]) or '(none)'}")
    problems = check_crates(packages, edges) + check_zenoh(packages)
    for p in packages:
        src = pathlib.Path(p["manifest_path"]).parent / "src"
        for comp in cycles(module_graph(src)):
            problems.append(f"{p['name']}: modules import each other in a circle: {' <-> '.join(comp)}")
    for problem in problems:
        print(problem, file=sys.stderr)
    if problems:
        sys.exit(1)
    print(f"layers ok: {len(packages)} crates, no upward dependency, no module circle, zenoh only in "
          f"{', '.join(sorted(ZENOH_ALLOWED & {p['name'] for p in packages}))}")


if __name__ == "__main__":
    main()
