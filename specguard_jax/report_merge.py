"""Several evaluate.py outputs made with the same missions, as one report (evaluate.py --merge DIR ...).

An evaluation too large for one job (many controllers at 1,000 missions per setting on a time-limited machine) runs
as parts that fly disjoint sets of controllers on the same seed, missions, worlds and settings; every part flies no
protection too (the twin of every metric). Merged, the parts give one report whose paired tests cover every pair of
controllers across the parts, exactly as if one job had flown them all: the missions are a function of the seed and
the settings only (evaluation.rollout), and this module refuses parts where that is not so (different flags, or the
same controller's per-mission records differing between two parts).

Inputs are each part's report.json (its meta, groups, controllers and red-team log) and records/<group>__<ctrl>.npz
(the per-mission records report.build reads); the output is report.build's (results, records, meta) triple.
"""

from __future__ import annotations

import json
import os

import numpy as np

# meta fields that fix which missions a part flew and how they were scored: equal in every part
SAME_META = ("seed", "missions_per_setting", "max_s", "mission_s", "profiles", "campaigns", "hazard_lead_s",
             "designed_rates", "mission_file", "params_file")
# group fields that must agree wherever two parts have the group
SAME_GROUP = ("vehicle", "worlds", "settings", "env")


def load_part(d: str) -> dict:
  """{'dir', 'report', 'records': {(group, controller): {field: array}}} of one evaluate.py output directory;
  ValueError (one line) naming the file that is missing or unreadable."""
  path = os.path.join(d, "report.json")
  try:
    with open(path) as f:
      rep = json.load(f)
  except (OSError, ValueError) as e:
    raise ValueError(f"--merge {d}: cannot read {path} ({type(e).__name__})") from None
  if not isinstance(rep, dict) or not isinstance(rep.get("groups"), dict) or not isinstance(rep.get("meta"), dict):
    raise ValueError(f"--merge {d}: {path} is not an evaluate.py report (no 'meta' / 'groups')")
  records = {}
  for g, grp in rep["groups"].items():
    for c in grp.get("controllers") or {}:
      rpath = os.path.join(d, "records", f"{g}__{c}.npz")
      try:
        with np.load(rpath) as z:
          records[(g, c)] = {k: z[k] for k in z.files}
      except (OSError, ValueError) as e:
        raise ValueError(f"--merge {d}: cannot read the records of {g}/{c} ({rpath}: {type(e).__name__})") from None
  return {"dir": d, "report": rep, "records": records}


def _same_records(a: dict, b: dict) -> bool:
  return set(a) == set(b) and all(np.array_equal(a[k], b[k], equal_nan=np.asarray(a[k]).dtype.kind == "f")
                                  for k in a)


def merge(parts: list[dict], command: str) -> tuple[dict, dict, dict]:
  """(results, records, meta) for report.build from load_part() outputs, in order (a controller flown by several
  parts is taken from the first). ValueError (one line) when the parts did not fly the same missions."""
  if len(parts) < 2:
    raise ValueError("--merge takes at least two evaluation directories")
  first = parts[0]
  for p in parts[1:]:
    for k in SAME_META:
      a, b = p["report"]["meta"].get(k), first["report"]["meta"].get(k)
      if a != b:
        raise ValueError(f"--merge: {p['dir']} and {first['dir']} differ in {k} ({a!r} vs {b!r}): not the same "
                         "missions")
  results = {"groups": {}, "not_run": {}, "skipped_experiments": {}, "rollouts": [], "compile_wall_s": 0.0}
  records, owner = {}, {}
  for p in parts:
    rep = p["report"]
    results["compile_wall_s"] += float((rep.get("totals") or {}).get("compile_s", 0.0))
    for g, grp in rep["groups"].items():
      have = results["groups"].get(g)
      if have is None:
        have = results["groups"][g] = {k: grp.get(k) for k in SAME_GROUP}
        have["controllers"] = {}
      else:
        for k in SAME_GROUP:
          if grp.get(k) != have[k]:
            raise ValueError(f"--merge: group {g} differs in {k} between {p['dir']} and an earlier part")
      for c, info in (grp.get("controllers") or {}).items():
        rec = p["records"][(g, c)]
        if (g, c) in records:
          if not _same_records(records[(g, c)], rec):
            raise ValueError(f"--merge: {g}/{c} flew differently in {p['dir']} and {owner[(g, c)]}: the parts did "
                             "not fly the same missions (on a GPU, fly every part with XLA_FLAGS="
                             "--xla_gpu_deterministic_ops=true: cold compiles may round differently)")
          continue
        records[(g, c)], owner[(g, c)] = rec, p["dir"]
        have["controllers"][c] = info
        results["rollouts"].append({"group": g, "controller": c, "missions": int(len(rec["complete"])),
                                    "compile_s": float(info.get("compile_s", 0.0)),
                                    "run_s": float(info.get("run_s", 0.0))})
    for key, why in (rep.get("not_run") or {}).items():
      results["not_run"].setdefault(key, why)
    for key, why in (rep.get("skipped_experiments") or {}).items():
      results["skipped_experiments"].setdefault(key, why)
    for c, log in (rep.get("redteam") or {}).items():
      if log.get("agent") is not None:
        results.setdefault("redteam", {}).setdefault(c, log["agent"])
  results["not_run"] = {k: v for k, v in results["not_run"].items() if tuple(k.split("/", 1)) not in records}
  results["skipped_experiments"] = {k: v for k, v in results["skipped_experiments"].items()
                                    if k not in results["groups"]}
  metas = [p["report"]["meta"] for p in parts]
  meta = dict(metas[0])
  commits = list(dict.fromkeys(str(m.get("git_commit")) for m in metas))
  meta.update(
      command=command, date=min(str(m.get("date")) for m in metas), git_commit=", ".join(commits),
      device=", ".join(dict.fromkeys(str(m.get("device")) for m in metas)),
      backend=", ".join(dict.fromkeys(str(m.get("backend")) for m in metas)),
      runs={k: v for m in metas for k, v in (m.get("runs") or {}).items()},
      recon_modes={k: v for m in metas for k, v in (m.get("recon_modes") or {}).items()},
      recovery_rules={k: v for m in metas for k, v in (m.get("recovery_rules") or {}).items()},
      baseline_builds={k: v for m in metas for k, v in (m.get("baseline_builds") or {}).items()},
      redteam=next((m["redteam"] for m in metas if m.get("redteam")), None),
      eval_wall_s=float(sum(m.get("eval_wall_s") or 0.0 for m in metas)),
      merged_from=[{"dir": p["dir"], "command": m.get("command"), "date": m.get("date"),
                    "git_commit": m.get("git_commit"), "device": m.get("device"),
                    "controllers": sorted({c for (_, c) in p["records"]})} for p, m in zip(parts, metas)])
  return results, records, meta
