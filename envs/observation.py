"""The policy's observation layouts: named, versioned lists of fields that the env, the trainer, the ONNX export and
evaluate.py agree on (a run writes its layout into policy_config.json; `specguard_jax.export`).

`paper24` (24 inputs, the layout every policy trained before the recovery context had): the paper's x'_t from the
ESTIMATED state (position relative to the target waypoint, velocity, acceleration, Euler angles) and the mission
context computed from that estimate against the map (next leg's direction, direction and distance to the nearest
obstacle, fence margin, path deviation, altitude, horizontal speed, waypoint slack).

`recovery` = paper24 + what the autopilot does not see, so that the policy can tell when its estimate is wrong:
  alarm [1]             the detector's alarm (0/1; 0 without a detector)
  diagnosed [6]         the sensors diagnosed compromised, a 0/1 mask in SENSOR_NAMES order
  time_since_alarm [1]  s since the alarm rose, capped at TIME_CAP_S (0 without alarm)
  estimate_std [4]      1-sigma of the estimate the autopilot flies on: position (m), velocity (m/s), tilt (rad), yaw
                        (rad), from the reconstruction's filter while the alarm is up, else the EKF's (capped)
  proximity [N]         a ring of N horizontal range sensors on the body (sector k at body yaw + 2 pi k / N), to
                        the nearest obstacle, keep-out fence or boundary edge, from the TRUE geometry and attitude
                        plus range noise, capped at the sensor's maximum range. Not attacked: the paper's threat
                        model spoofs the navigation sensors; its S1 monitor reads distance sensors, and the authors'
                        released environment gives its policy six range sensors.
`context` = recovery + the mission phase the navigator is in (specs S3, S5, S7, S9, S10, S11 hold in some phases
only, S9's 0.5 m/s landing limit among them: without it the policy cannot tell a landing from a climb-out):
  phase [4]             one-hot of takeoff, cruise, loiter, descent (all 0 once the mission is done)
The first 24 entries are the same in every layout (the attack agent reads x'_t and the obstacle distance there).

History (`history` H > 1, EnvConfig.obs_history): the layout's frame is followed by the H - 1 frames before it,
newest first ([frame_t, frame_t-1, ..., frame_t-H+1], one field `previous_frames` of (H - 1) x the frame's size;
the first step of an episode repeats its frame). The current frame stays first, so everything that reads the
first entries reads the present.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from specguard_jax.autopilot.navigator import PHASE_NAMES
from specguard_jax.types import SENSOR_NAMES

LAYOUT_VERSION = 1
LAYOUTS = ("paper24", "recovery", "context")
PHASES = len(PHASE_NAMES) - 1   # every navigator phase but "done"
TIME_CAP_S = 60.0
STD_CAP = 100.0

PAPER24_FIELDS = (("pos_rel_target", 3), ("vel", 3), ("acc", 3), ("euler", 3), ("next_leg_dir", 3),
                  ("obstacle_dir", 3), ("obstacle_distance", 1), ("fence_margin", 1), ("path_deviation", 1),
                  ("altitude", 1), ("speed_xy", 1), ("wp_slack", 1))


@dataclasses.dataclass(frozen=True)
class RangeSensorConfig:
  """The proximity ring's range noise: sigma = sigma_m + sigma_frac x range (m). Defaults from the Terabee
  TeraRanger Evo 60m datasheet (the sensor of the TeraRanger Tower's 8-sector ring): +-4 cm accuracy to 14 m,
  +-1.5 % beyond, read here as 1-sigma."""
  sigma_m: float = 0.04
  sigma_frac: float = 0.015


def frame_fields(layout: str, sectors: int) -> tuple:
  """((name, size), ...) of one frame of `layout` with a proximity ring of `sectors` beams."""
  if layout == "paper24":
    return PAPER24_FIELDS
  recovery = PAPER24_FIELDS + (("alarm", 1), ("diagnosed", len(SENSOR_NAMES)), ("time_since_alarm", 1),
                                ("estimate_std", 4), ("proximity", int(sectors)))
  if layout == "recovery":
    return recovery
  if layout == "context":
    return recovery + (("phase", PHASES),)
  raise ValueError(f"unknown observation layout {layout!r}; choose one of {', '.join(LAYOUTS)}")


def fields(layout: str, sectors: int, history: int = 1) -> tuple:
  """((name, size), ...) of `layout` with a proximity ring of `sectors` beams and `history` frames (module
  docstring: the frames before the current one are one field, previous_frames)."""
  frame = frame_fields(layout, sectors)
  if history > 1:
    return frame + (("previous_frames", (int(history) - 1) * sum(n for _, n in frame)),)
  return frame


def size(layout: str, sectors: int, history: int = 1) -> int:
  """Number of observation entries of `layout` (with `history` frames)."""
  return sum(n for _, n in fields(layout, sectors, history))


def frame_size(layout: str, sectors: int) -> int:
  """Number of entries of one frame of `layout`."""
  return sum(n for _, n in frame_fields(layout, sectors))


def describe(layout: str, sectors: int, history: int = 1) -> dict:
  """The layout as policy_config.json records it: {'name', 'version', 'fields': [[name, size], ...]}."""
  return {"name": layout, "version": LAYOUT_VERSION, "fields": [[f, n] for f, n in fields(layout, sectors, history)]}


def sectors_of(desc: dict) -> int:
  """The proximity ring's sector count of a `describe` dict (0 without a ring)."""
  return dict((f, n) for f, n in desc["fields"]).get("proximity", 0)


def history_of(desc: dict) -> int:
  """The number of frames of a `describe` dict (1 without previous_frames)."""
  sizes = dict((f, n) for f, n in desc["fields"])
  frame = sum(n for f, n in desc["fields"] if f != "previous_frames")
  return 1 + sizes.get("previous_frames", 0) // max(frame, 1)


def with_history(frame: jax.Array, previous_obs: jax.Array | None, history: int) -> jax.Array:
  """The observation [history x F] of this step's frame [F]: the frame, then the newest history - 1 frames of the
  previous observation (its first (history - 1) x F entries); previous_obs None (an episode's first step): the
  frame repeated."""
  if history <= 1:
    return frame
  if previous_obs is None:
    return jnp.tile(frame, history)
  return jnp.concatenate([frame, previous_obs[: (history - 1) * frame.shape[-1]]])


def noisy_ranges(ranges: jax.Array, key: jax.Array, max_range: float, cfg: RangeSensorConfig) -> jax.Array:
  """ranges [N] (m) as the range sensors read them: Gaussian noise with the datasheet's sigma, clipped to
  [0, max_range]."""
  sigma = cfg.sigma_m + cfg.sigma_frac * ranges
  return jnp.clip(ranges + sigma * jax.random.normal(key, ranges.shape), 0.0, max_range)


def phase_one_hot(phase) -> jax.Array:
  """The `context` layout's phase entries [PHASES] float32: one-hot of the navigator's phase (0 when done)."""
  return jax.nn.one_hot(jnp.asarray(phase, jnp.int32), PHASES, dtype=jnp.float32)


def recovery_context(alarm, diagnosed, time_since_alarm, estimate_std, proximity) -> jax.Array:
  """The `recovery` layout's entries after the first 24, [1 + 6 + 1 + 4 + N] float32 (see the module docstring)."""
  return jnp.concatenate([
      jnp.reshape(jnp.asarray(alarm, jnp.float32), (1,)), jnp.asarray(diagnosed, jnp.float32),
      jnp.reshape(jnp.minimum(jnp.asarray(time_since_alarm, jnp.float32), TIME_CAP_S), (1,)),
      jnp.minimum(jnp.nan_to_num(jnp.asarray(estimate_std, jnp.float32), nan=STD_CAP), STD_CAP),
      jnp.asarray(proximity, jnp.float32)])
