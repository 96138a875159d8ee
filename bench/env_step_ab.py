"""Same-call A/B of the env step between source trees (git revisions): ms per `Vmap(env).step`, each tree timed in a
process of its own, so two versions of the library run on the same machine within a minute of each other (GPU
timings drift by 1-2 % between machine starts; the changes this bench decides on are often that small).

Each tree holds `specguard_jax/`, `envs/` and `assets/` of one revision: `--make-trees DIR REV [REV ...]` writes them
(`git archive`, needs the repository's history: make them where you commit and carry DIR to the GPU machine), then
`python bench/env_step_ab.py DIR/REV1 DIR/REV2 [DIR/REV1 ...] --vehicle rover`. A tree may repeat (A B A: the drift).

Timing: the env as the trainer configures it (`ppo/iteration.trainer_env_options("none")`: no NaN fallback, no EKF
records; `--defaults`: EnvConfig's defaults), phase 1, zero action, a jitted `lax.scan` of --steps steps; the best of
--calls calls after the compile call. Prints one line per tree: ms per env step, the first call's seconds (compile
and one call) and the observation / reward sums of the last state (equal across trees whose change keeps values).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def make_trees(out: str, revs: list[str]) -> None:
  """git archive of each revision's library into out/<rev>."""
  for rev in revs:
    d = os.path.join(out, rev.replace("/", "_"))
    os.makedirs(d, exist_ok=True)
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev, "specguard_jax", "envs", "assets"],
                             capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", d], input=archive, check=True)
    print(d)


def time_here(args) -> None:
  """Times the env step of the library importable from the working directory (run inside a tree)."""
  import jax
  import jax.numpy as jnp
  import envs
  from specguard_jax.ppo.iteration import trainer_env_options

  kw = {} if args.defaults else trainer_env_options("none")
  if args.ekf_kernel is not None:
    kw["ekf_kernel"] = args.ekf_kernel
  env = envs.make(args.vehicle, **kw)
  n = args.envs
  state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(args.seed), n))
  act = jnp.zeros((n, env.action_size))
  run = jax.jit(lambda s: jax.lax.scan(lambda c, _: (jax.vmap(env.step)(c, act), None), s, None,
                                       length=args.steps)[0])
  t = time.perf_counter()
  out = jax.block_until_ready(run(state))
  first = time.perf_counter() - t
  best = float("inf")
  for _ in range(args.calls):
    t = time.perf_counter()
    jax.block_until_ready(run(state))
    best = min(best, (time.perf_counter() - t) / args.steps)
  print(f"{best * 1e3:.3f} ms per env step (first call {first:.1f} s), obs sum {float(jnp.sum(jnp.abs(out.obs))):.6g}, "
        f"reward sum {float(jnp.sum(out.reward)):.6g}", flush=True)


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("trees", nargs="*", help="source trees to time, in this order")
  p.add_argument("--make-trees", nargs="+", metavar=("DIR", "REV"), help="write DIR/<rev> for each REV and exit")
  p.add_argument("--vehicle", choices=("drone", "rover"), default="drone")
  p.add_argument("--envs", type=int, default=65536)
  p.add_argument("--steps", type=int, default=32, help="env steps per timed call")
  p.add_argument("--calls", type=int, default=5, help="timed calls after the compile call (best one kept)")
  p.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default=None,
                 help="EnvConfig.ekf_kernel (default: EnvConfig's default)")
  p.add_argument("--defaults", action="store_true", help="EnvConfig's defaults instead of the trainer's env")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--timeout", type=float, default=300.0, help="seconds per tree")
  p.add_argument("--here", action="store_true", help=argparse.SUPPRESS)
  args = p.parse_args()
  if args.make_trees:
    if len(args.make_trees) < 2:
      p.error("--make-trees needs DIR and at least one REV")
    make_trees(args.make_trees[0], args.make_trees[1:])
    return
  if args.here:
    time_here(args)
    return
  if not args.trees:
    p.error("give at least one source tree (see --make-trees)")
  for tree in args.trees:
    if not os.path.isdir(os.path.join(tree, "specguard_jax")) or not os.path.isdir(os.path.join(tree, "envs")):
      p.error(f"{tree}: not a source tree (no specguard_jax/ and envs/ in it)")
  flags = [a for a in sys.argv[1:] if a not in args.trees]
  for tree in args.trees:
    tree = os.path.abspath(tree)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([tree] + [x for x in os.environ.get("PYTHONPATH", "").split(
        os.pathsep) if x and os.path.abspath(x) != ROOT]))
    try:
      r = subprocess.run([sys.executable, os.path.abspath(__file__), "--here", *flags], cwd=tree, env=env,
                         capture_output=True, text=True, timeout=args.timeout)
      line = r.stdout.strip().splitlines()[-1] if r.returncode == 0 and r.stdout.strip() else (
          f"failed (rc {r.returncode}): " + (r.stderr.strip().splitlines() or ["no output"])[-1])
    except subprocess.TimeoutExpired:
      line = f"timed out after {args.timeout:.0f} s"
    print(f"{os.path.basename(tree)} {args.vehicle} {args.envs}: {line}", flush=True)


if __name__ == "__main__":
  main()
