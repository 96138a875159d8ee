"""The import structure: no cycles among the library's modules, and imports run down the layers only.

Layers (bottom up): the core (every specguard_jax module not named in ABOVE_ENVS: math3d, types, sensors, ekf, stl,
specs, rewards, autopilot, attacks, detection, estimation, metrics, ...) < envs < the modules built on envs
(ABOVE_ENVS) < the CLIs (train.py, evaluate.py). Imports are read from the sources with ast, imports inside functions
included, so a cycle cannot hide in a function body.
"""

from __future__ import annotations

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("specguard_jax", "envs")
# specguard_jax's top-level modules / subpackages that build on envs.
ABOVE_ENVS = ("ppo", "evaluation", "baselines", "controllers", "report", "export", "calibration", "cli")


def _modules() -> dict:
  """{dotted module name: path} of every module of PACKAGES."""
  out = {}
  for pkg in PACKAGES:
    for path in sorted((ROOT / pkg).rglob("*.py")):
      parts = list(path.relative_to(ROOT).with_suffix("").parts)
      if parts[-1] == "__init__":
        parts = parts[:-1]
      out[".".join(parts)] = path
  return out


def _owner(name: str, modules: dict) -> str | None:
  """The module of `modules` that an imported dotted name lives in (None: outside the library)."""
  while name and name not in modules:
    name = name.rpartition(".")[0]
  return name or None


def import_graph() -> dict:
  """{module: {(imported module, line)}} over every import statement, at any depth."""
  modules = _modules()
  graph = {}
  for mod, path in modules.items():
    is_pkg = path.name == "__init__.py"
    edges = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
      names = []
      if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
      elif isinstance(node, ast.ImportFrom):
        if node.level:
          base = mod.split(".") if is_pkg else mod.split(".")[:-1]
          base = base[:len(base) - (node.level - 1)]
          src = ".".join(base + ([node.module] if node.module else []))
        else:
          src = node.module
        names = [f"{src}.{a.name}" if f"{src}.{a.name}" in modules else src for a in node.names]
      for n in names:
        target = _owner(n, modules)
        if target and target != mod:
          edges.add((target, node.lineno))
    graph[mod] = edges
  return graph


def _layer(mod: str) -> int:
  """0 core, 1 envs, 2 built on envs."""
  if mod.split(".")[0] == "envs":
    return 1
  parts = mod.split(".")
  return 2 if len(parts) > 1 and parts[1] in ABOVE_ENVS else 0


def find_cycles(graph: dict) -> list:
  """Strongly connected components of more than one module (Tarjan, iterative)."""
  index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
  adj = {m: sorted({t for t, _ in e}) for m, e in graph.items()}
  for root in adj:
    if root in index:
      continue
    work = [(root, iter(adj[root]))]
    index[root] = low[root] = counter[0]
    counter[0] += 1
    stack.append(root)
    on.add(root)
    while work:
      v, it = work[-1]
      w = next(it, None)
      if w is not None:
        if w not in index:
          index[w] = low[w] = counter[0]
          counter[0] += 1
          stack.append(w)
          on.add(w)
          work.append((w, iter(adj.get(w, ()))))
        elif w in on:
          low[v] = min(low[v], index[w])
        continue
      work.pop()
      if work:
        low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
  return out


def test_the_graph_sees_function_level_imports(tmp_path):
  g = import_graph()
  assert any(t == "envs.base" for t, _ in g["envs.rollout"])
  assert find_cycles({"a": {("b", 1)}, "b": {("c", 2)}, "c": {("a", 3)}, "d": {("a", 4)}}) == [["a", "b", "c"]]
  assert find_cycles({"a": {("b", 1)}, "b": set()}) == []


def test_no_import_cycles():
  cycles = find_cycles(import_graph())
  assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_imports_run_down_the_layers():
  names = ("core", "envs", "built on envs")
  bad = [f"{mod} ({names[_layer(mod)]}) imports {target} ({names[_layer(target)]}), line {line}"
         for mod, edges in import_graph().items() for target, line in sorted(edges)
         if _layer(target) > _layer(mod)]
  assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_private_env_members_outside_envs():
  """Outside envs/ the library reaches the env through its public API (envs.make, reset/step, envs.record, ...):
  no `env._tick`, `env._observation`, ... on a name that holds an env."""
  bad = []
  for mod, path in _modules().items():
    if mod.split(".")[0] == "envs":
      continue
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
      if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
          and isinstance(node.value, ast.Name) and "env" in node.value.id.lower()):
        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value.id}.{node.attr}")
  assert not bad, "private env members used outside envs/:\n" + "\n".join(bad)


def _module_aliases(tree, mod: str, modules: dict) -> dict:
  """{local name: library module} bound by the import statements of `tree` (any depth)."""
  out = {}
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      for a in node.names:
        if a.asname and _owner(a.name, modules) == a.name:
          out[a.asname] = a.name
        elif not a.asname and a.name.split(".")[0] in PACKAGES:
          out[a.name.split(".")[0]] = a.name.split(".")[0]
    elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
      for a in node.names:
        full = f"{node.module}.{a.name}"
        if full in modules:
          out[a.asname or a.name] = full
  return out


def test_no_private_members_of_other_modules():
  """Library code, tools, benches and experiments call other modules through their public names only: no
  `ekf_lib._fuse`, `dyn._ridge`, ... (tests may reach into a module's internals)."""
  modules = _modules()
  files = dict(modules)
  for extra in ("bench", "tools", "experiments"):
    files.update({f"{extra}.{p.stem}": p for p in sorted((ROOT / extra).glob("*.py"))})
  bad = []
  for mod, path in files.items():
    tree = ast.parse(path.read_text(), str(path))
    aliases = _module_aliases(tree, mod, modules)
    for node in ast.walk(tree):
      if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
          and isinstance(node.value, ast.Name) and node.value.id in aliases and aliases[node.value.id] != mod):
        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value.id}.{node.attr}")
  assert not bad, "private members of other modules used:\n" + "\n".join(bad)
