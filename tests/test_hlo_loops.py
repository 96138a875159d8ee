"""bench/hlo_loops.py: while loops of an optimised HLO module and the copies in their bodies."""

import os
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))
import hlo_loops  # noqa: E402

HLO = """
HloModule m
%body (p: (s32[], f32[16,3], f32[16])) -> (s32[], f32[16,3], f32[16]) {
  %p = (s32[], f32[16,3]{1,0}, f32[16]{0}) parameter(0)
  %get-tuple-element.1 = f32[16,3]{1,0} get-tuple-element(%p), index=1
  %copy.7 = f32[16,3]{1,0} copy(%get-tuple-element.1)
  %fusion.2 = f32[16]{0} fusion(%copy.7), kind=kLoop, calls=%f, metadata={op_name="jit(run)/while/body/navigator/gather"}
  ROOT %tuple.3 = (s32[], f32[16,3]{1,0}, f32[16]{0}) tuple(%c, %x, %fusion.2)
}
ENTRY %main {
  %while.1 = (s32[], f32[16,3]{1,0}, f32[16]{0}) while(%t), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"4"}}
}
"""


def test_loops_copies_slots_and_users():
  (lp,) = hlo_loops.while_loops(HLO)
  assert (lp["body"], lp["parent"], lp["trip"], lp["fusions"]) == ("body", "main", 4, 1)
  (name, shape, operand, slot, users), = lp["copies"]
  assert (name, operand, slot) == ("copy.7", "get-tuple-element.1", 1)
  assert hlo_loops.nbytes(shape) == 16 * 3 * 4
  assert users == ["jit(run)/while/body/navigator/gather"]


def test_finds_the_loop_of_a_compiled_scan(capsys, tmp_path):
  f = jax.jit(lambda x: jax.lax.fori_loop(0, 7, lambda i, c: (c[1], c[0] * 2.0 + jnp.sin(c[1])), (x, x + 1.0)))
  text = f.lower(jnp.ones(8)).compile().as_text()
  loops = hlo_loops.while_loops(text)
  assert len(loops) >= 1 and all(lp["instructions"] > 0 for lp in loops)
  path = tmp_path / "m.hlo"
  path.write_text(text)
  hlo_loops.main([str(path)])
  assert f"{len(loops)} while loops" in capsys.readouterr().out
