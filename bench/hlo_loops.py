"""The while loops of an optimised HLO module and the copies XLA put in their bodies.

  python bench/gpu_profile.py --envs 16384 --phase 2 --hlo-out /tmp/p2.hlo   # on the GPU: the HLO of a training call
  python bench/hlo_loops.py /tmp/p2.hlo [--all]                              # its loops, trip counts, copies

A copy in a loop body is a kernel per iteration (on a GPU ~1.5-2 us at 16,384 envs, plus its launch gap): XLA adds one
where a loop-carried value is read after its new value could be written in place (a read it cannot order before the
write), or where the carry swaps values between slots. Each copy is listed with its shape and, when it copies a
loop-carried value, the carry slot (tuple index), and the op_names of its first users, to find the code behind it.
"""

from __future__ import annotations

import argparse
import re
import sys

_BYTES = {"f32": 4, "s32": 4, "u32": 4, "pred": 1, "bf16": 2, "f16": 2, "u8": 1, "s8": 1, "f64": 8, "s64": 8,
          "u64": 8}


def computations(hlo_text: str) -> dict:
  """{computation name: its instruction lines}."""
  comps, cur = {}, None
  for line in hlo_text.splitlines():
    if line and not line[0].isspace():
      if line.rstrip().endswith("{"):
        m = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)", line)
        cur = m.group(1)
        comps[cur] = []
      continue
    if cur is not None:
      comps[cur].append(line)
  return comps


def nbytes(shape: str) -> int:
  """Bytes of an HLO array shape like f32[1,16384,3]{2,1,0} (0 for tuples and unknown types)."""
  m = re.match(r"(\w+)\[([\d,]*)\]", shape)
  if not m:
    return 0
  n = 1
  for d in filter(None, m.group(2).split(",")):
    n *= int(d)
  return n * _BYTES.get(m.group(1), 4)


def while_loops(hlo_text: str) -> list:
  """One dict per while instruction: body, parent computation, trip (known trip count or None), instructions,
  fusions, and copies: [(name, shape, operand, carry slot or None, [op_names of up to 3 users])]."""
  comps = computations(hlo_text)
  out = []
  for parent, lines in comps.items():
    for line in lines:
      if " while(" not in line:
        continue
      body = re.search(r"body=%?([\w.\-]+)", line).group(1)
      trip = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
      blines = comps.get(body, [])
      defs = {}
      for x in blines:
        m = re.match(r"\s*(?:ROOT\s+)?%([\w.\-]+) = ", x)
        if m:
          defs[m.group(1)] = x
      slot = {n: int(m.group(1)) for n, x in defs.items()
              if (m := re.search(r"get-tuple-element\(%[\w.\-]+\), index=(\d+)", x))}
      copies = []
      for name, x in defs.items():
        m = re.search(r"= (\S+) copy\(%([\w.\-]+)\)", x)
        if not m:
          continue
        users = []
        for u, ux in defs.items():
          if u != name and re.search(r"%" + re.escape(name) + r"\b", ux.split(" = ", 1)[1]):
            on = re.search(r'op_name="([^"]*)"', ux)
            users.append(on.group(1) if on else u)
        copies.append((name, m.group(1), m.group(2), slot.get(m.group(2)), users[:3]))
      out.append(dict(body=body, parent=parent, trip=int(trip.group(1)) if trip else None, instructions=len(defs),
                      fusions=sum(1 for x in defs.values() if re.search(r"= \S+ fusion\(", x)), copies=copies))
  return out


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("hlo", help="optimised HLO text (gpu_profile.py --hlo-out)")
  ap.add_argument("--all", action="store_true", help="list every copy (default: the 12 largest of each loop)")
  a = ap.parse_args(argv)
  loops = while_loops(open(a.hlo).read())
  print(f"{len(loops)} while loops")
  print("| body | in | trip count | instructions | fusions | copies | copied bytes per iteration |")
  print("|---|---|---:|---:|---:|---:|---:|")
  for lp in loops:
    print(f"| {lp['body'][:40]} | {lp['parent'][:30]} | {lp['trip'] or '?'} | {lp['instructions']} | {lp['fusions']} "
          f"| {len(lp['copies'])} | {sum(nbytes(c[1]) for c in lp['copies']):,} |")
  for lp in loops:
    if not lp["copies"]:
      continue
    print(f"\n{lp['body']} (trip {lp['trip'] or '?'}):")
    cps = sorted(lp["copies"], key=lambda c: -nbytes(c[1]))
    for name, shape, operand, slot, users in cps if a.all else cps[:12]:
      where = f"carry slot {slot}" if slot is not None else f"of {operand}"
      print(f"  {name} {shape} ({where}); used by: {'; '.join(u[-90:] for u in users) or 'the loop output'}")


if __name__ == "__main__":
  sys.exit(main())
