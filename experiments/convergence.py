"""Time to convergence of training runs (the paper's Fig. 3a: SpecGuard-RC converges faster than SpecGuard-PC).

  python experiments/convergence.py --runs rc=runs/rc pc=runs/pc [--window W] [--eps E] [--plot OUT.png]
                                    [--json OUT]

Per run (a train.py run directory: metrics.jsonl, config.json): the first phase-2 iteration at which the paper's
Algorithm 2 stop rule holds (ppo.runner.converged: both agents' mean returns change by less than eps per iteration
between the last two windows of W iterations), with the run's converge_window / converge_eps unless --window / --eps
are given, checked where the trainer checks it (after each call of the run's iters_per_call iterations; the rule
can hold at one iteration and not at the next); the env steps and training seconds to that iteration (the sum of
the iterations' steps / their calls' steps per second, a phase's first call at the next call's rate: compiles
excluded); and the run's phase-2 return and SVR averaged over its last window. A run that never meets the rule says
so ("not within its budget"): a run trained with the stop rule on ends where it converged, one trained without it
(converge_eps=0 or a sweep) is judged here on the rule it would have stopped by. Compare runs trained on the same
budget and env count, on the same device.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys


def load_run(run_dir: str) -> dict:
  """{'rows': metrics.jsonl records, 'window', 'eps', 'every' (iters_per_call)} of a run directory; ValueError (one
  line) naming the file."""
  path = os.path.join(run_dir, "metrics.jsonl")
  try:
    with open(path) as f:
      rows = [json.loads(line) for line in f if line.strip()]
  except (OSError, ValueError) as e:
    raise ValueError(f"{path}: cannot read the run's metrics ({type(e).__name__}: {e})") from None
  if not rows or any(not isinstance(r, dict) or "phase" not in r or "env_steps" not in r for r in rows):
    raise ValueError(f"{path}: no metrics records with 'phase' and 'env_steps'")
  window, eps, every = 20, 1e-3, 1
  cfg_path = os.path.join(run_dir, "config.json")
  if os.path.isfile(cfg_path):
    try:
      with open(cfg_path) as f:
        cfg = json.load(f)
      window, eps = int(cfg.get("converge_window", window)), float(cfg.get("converge_eps", eps))
      every = max(1, int(cfg.get("iters_per_call", every)))
    except (OSError, ValueError, TypeError) as e:
      raise ValueError(f"{cfg_path}: cannot read the run's config ({type(e).__name__}: {e})") from None
  return {"rows": rows, "window": window, "eps": eps, "every": every}


def _finite(x) -> float:
  return float(x) if x is not None and math.isfinite(float(x)) else float("nan")


def time_to_convergence(rows: list, window: int, eps: float, every: int = 1) -> dict:
  """The first phase-2 iteration, among every `every`-th, at which runner.converged holds on the returns logged so
  far: {'iteration' (None
  when never), 'env_steps', 'train_s' (phase 2 only, to that iteration or to the end), 'phase2_iterations',
  'return', 'svr' (means over the last `window` phase-2 iterations up to it)}."""
  from specguard_jax.ppo.runner import converged
  p2 = [r for r in rows if r.get("phase") == 2]
  start = max([r["env_steps"] for r in rows if r.get("phase") == 1], default=0)
  history, at, train_s, prev = [], None, 0.0, start
  # a call's first iterations (first_call) log steps / (compile + run): their rate is the next call's
  steady = [_finite(r.get("sps")) for r in p2]
  for i in range(len(p2) - 2, -1, -1):
    if p2[i].get("first_call"):
      steady[i] = steady[i + 1]
  for i, r in enumerate(p2):
    sps = steady[i]
    train_s += (r["env_steps"] - prev) / sps if sps > 0 else 0.0
    prev = r["env_steps"]
    history.append([_finite(r.get("return")), _finite(r.get("return_aa"))])
    if (i + 1) % every == 0 and converged(history, window, eps):
      at = i
      break
  end = at if at is not None else len(p2) - 1
  last = p2[max(0, end - window + 1): end + 1]

  def mean(key):
    vals = [_finite(r.get(key)) for r in last]
    vals = [v for v in vals if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else None

  return {"iteration": (p2[at].get("iteration", at + 1) if at is not None else None),
          "env_steps": (p2[end]["env_steps"] - start) if p2 else 0, "train_s": train_s,
          "phase2_iterations": len(p2), "return": mean("return"), "svr": mean("svr"), "window": window, "eps": eps}


def _plot(runs: dict, results: dict, path: str) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(7, 4))
  for name, run in runs.items():
    rows = [r for r in run["rows"] if r.get("phase") == 2]
    start = max([r["env_steps"] for r in run["rows"] if r.get("phase") == 1], default=0)
    line, = ax.plot([(r["env_steps"] - start) / 1e6 for r in rows], [_finite(r.get("return")) for r in rows],
                    label=name)
    res = results[name]
    if res["iteration"] is not None:
      ax.axvline(res["env_steps"] / 1e6, color=line.get_color(), ls="--", lw=1)
  ax.set_xlabel("phase-2 env steps (M)")
  ax.set_ylabel("SpecGuard return per episode")
  ax.set_title("Time to convergence (dashed: Algorithm 2's stop rule met)")
  ax.legend()
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--runs", nargs="+", required=True, metavar="NAME=DIR", help="train.py run directories to compare")
  p.add_argument("--window", type=int, default=None, help="iterations per window (default: each run's own)")
  p.add_argument("--eps", type=float, default=None, help="relative change per iteration (default: each run's own)")
  p.add_argument("--plot", default=None, metavar="PNG", help="draw phase 2's return against env steps")
  p.add_argument("--json", default=None, metavar="OUT")
  a = p.parse_args(argv)
  if a.window is not None and a.window < 1:
    p.error(f"--window {a.window} is not allowed; allowed: >= 1")
  if a.eps is not None and not (a.eps > 0 and math.isfinite(a.eps)):
    p.error(f"--eps {a.eps} is not allowed; allowed: a finite number > 0")
  runs, results = {}, {}
  for item in a.runs:
    name, sep, d = item.partition("=")
    if not sep or not name or not d:
      p.error(f"--runs: bad item {item!r}; expected NAME=DIR")
    try:
      runs[name] = load_run(d)
    except ValueError as e:
      p.error(str(e))
    run = runs[name]
    results[name] = time_to_convergence(run["rows"], a.window or run["window"], a.eps or run["eps"], run["every"])
  print("| run | converged at phase-2 iteration | env steps (M) | training s | return | SVR | window / eps | "
        "trained phase-2 iterations |")
  print("|---|---|---|---|---|---|---|---|")
  for name, r in results.items():
    it = r["iteration"] if r["iteration"] is not None else f"not within its budget ({r['phase2_iterations']})"
    ret = f"{r['return']:.1f}" if r["return"] is not None else "n/a"
    svr = f"{r['svr']:.3f}" if r["svr"] is not None else "n/a"
    print(f"| {name} | {it} | {r['env_steps'] / 1e6:.2f} | {r['train_s']:.1f} | {ret} | {svr} | "
          f"{r['window']} / {r['eps']:g} | {r['phase2_iterations']} |")
  if a.plot:
    _plot(runs, results, a.plot)
  if a.json:
    with open(a.json, "w") as f:
      json.dump(results, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
