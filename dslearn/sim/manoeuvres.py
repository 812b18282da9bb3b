r"""Target trajectories S1-S3, sensor fields and measurements (paper Sec. V-A, V-C).

All generators are vectorised over ``R`` Monte Carlo runs (the loop is over time only) and
return positions ``(R, T, 2)`` and velocities ``(R, T, 2)`` in metres / m/s, sampled every
``dt`` seconds. Each trajectory is translated so that its bounding box is centred on the origin,
which is also the centre of the square area of interest (the GP's zero mean therefore sits at
the centre of the area).

* **S1** nearly-constant velocity (NCV, small white-acceleration noise) with *abrupt* velocity
  changes (speed and heading) at predefined turning points.
* **S2** Singer acceleration model: acceleration per axis is a first-order Markov process
  :math:`a_{k+1} = \rho a_k + \sqrt{1-\rho^2}\,\sigma_a w_k`, :math:`\rho = e^{-\Delta t/\tau}`,
  with Singer's variance :math:`\sigma_a^2 = \tfrac{A_{max}^2}{3}(1 + 4P_{max} - P_0)`
  (A_max = 50 m/s^2, P_0 = 0.4, P_max = 0), clipped to :math:`\pm A_{max}`. A pure Singer
  model with these values leaves any area 200 sensors of 50 m range can cover within a few
  seconds (median extent > 20 km over 100 s), so the speed is limited to ``v_max`` (documented
  deviation).
* **S3** coordinated turns: straight legs and sharp turns of 30 deg/s lasting 9 s, alternating
  left and right, plus small NCV noise.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

SCENARIOS = ("s1", "s2", "s3")


def _centre(pos: Tensor) -> Tensor:
    lo, hi = pos.amin(1, keepdim=True), pos.amax(1, keepdim=True)
    return pos - 0.5 * (lo + hi)


def generate_s1(runs: int, steps: int, gen: torch.Generator, *, dt=1.0, turn_every=20,
                speeds=(12.0, 8.0, 14.0, 10.0, 12.0), headings_deg=(0.0, 110.0, 200.0, 290.0, 30.0),
                accel_std=0.05, dtype=torch.float64, device="cpu"):
    """S1: NCV with abrupt velocity changes every ``turn_every`` steps (cycling the schedule).

    Returns:
        pos, vel: ``(runs, steps, 2)``.
    """
    nseg = len(speeds)
    pos = torch.zeros(runs, 2, dtype=dtype, device=device)
    out_p, out_v = [], []
    vel = None
    for k in range(steps):
        if k % turn_every == 0:  # predefined turning point: abrupt velocity change
            j = (k // turn_every) % nseg
            h = math.radians(headings_deg[j])
            vel = torch.tensor([math.cos(h), math.sin(h)], dtype=dtype, device=device) * speeds[j]
            vel = vel.expand(runs, 2).clone()
        w = torch.randn(runs, 2, generator=gen, dtype=dtype, device=device) * accel_std
        if k > 0:
            pos = pos + vel * dt + 0.5 * w * dt ** 2
            vel = vel + w * dt
        out_p.append(pos)
        out_v.append(vel)
    return _centre(torch.stack(out_p, 1)), torch.stack(out_v, 1)


def singer_sigma(a_max: float, p_zero: float, p_max: float = 0.0) -> float:
    """Singer's acceleration std :math:`\\sigma_a = \\sqrt{A_{max}^2/3\\,(1 + 4P_{max} - P_0)}`."""
    return math.sqrt(a_max ** 2 / 3.0 * (1.0 + 4.0 * p_max - p_zero))


def generate_s2(runs: int, steps: int, gen: torch.Generator, *, dt=1.0, a_max=50.0, p_zero=0.4,
                p_max=0.0, tau=10.0, v0=10.0, v_max=15.0, dtype=torch.float64, device="cpu"):
    """S2: Singer acceleration model (see module docstring), speed limited to ``v_max``.

    Returns:
        pos, vel: ``(runs, steps, 2)``.
    """
    rho = math.exp(-dt / tau)
    sa = singer_sigma(a_max, p_zero, p_max)
    h = torch.rand(runs, generator=gen, dtype=dtype, device=device) * 2 * math.pi
    vel = torch.stack([h.cos(), h.sin()], -1) * v0
    acc = torch.zeros(runs, 2, dtype=dtype, device=device)
    pos = torch.zeros(runs, 2, dtype=dtype, device=device)
    out_p, out_v = [], []
    for k in range(steps):
        if k > 0:
            w = torch.randn(runs, 2, generator=gen, dtype=dtype, device=device)
            acc = (rho * acc + math.sqrt(1 - rho ** 2) * sa * w).clamp(-a_max, a_max)
            new_vel = vel + acc * dt
            sp = new_vel.norm(dim=-1, keepdim=True)
            new_vel = new_vel * torch.clamp(v_max / sp.clamp_min(1e-12), max=1.0)
            pos = pos + 0.5 * (vel + new_vel) * dt
            vel = new_vel
        out_p.append(pos)
        out_v.append(vel)
    return _centre(torch.stack(out_p, 1)), torch.stack(out_v, 1)


def s3_turn_rates(steps: int, dt=1.0, turn_rate_deg=30.0, turn_duration=9.0, straight=12.0,
                  first_straight=8.0) -> list[float]:
    """Turn rate (rad/s) per step: straight, left turn, straight, right turn, ... (S3 schedule)."""
    rates, k, sign = [], 0, 1.0
    n_turn = int(round(turn_duration / dt))
    n_str0, n_str = int(round(first_straight / dt)), int(round(straight / dt))
    rates += [0.0] * n_str0
    while len(rates) < steps:
        rates += [sign * math.radians(turn_rate_deg)] * n_turn + [0.0] * n_str
        sign = -sign
    return rates[:steps]


def generate_s3(runs: int, steps: int, gen: torch.Generator, *, dt=1.0, speed=10.0,
                turn_rate_deg=30.0, turn_duration=9.0, straight=12.0, accel_std=0.05,
                dtype=torch.float64, device="cpu"):
    """S3: coordinated turns (exact CT discretisation) with left/right 30 deg/s, 9 s turns.

    Returns:
        pos, vel: ``(runs, steps, 2)``; the heading change over a turning step is exactly
        ``turn_rate * dt`` before the small NCV noise.
    """
    rates = s3_turn_rates(steps, dt, turn_rate_deg, turn_duration, straight)
    h = torch.rand(runs, generator=gen, dtype=dtype, device=device) * 2 * math.pi
    vel = torch.stack([h.cos(), h.sin()], -1) * speed
    pos = torch.zeros(runs, 2, dtype=dtype, device=device)
    out_p, out_v = [], []
    for k in range(steps):
        if k > 0:
            om = rates[k]
            if om == 0.0:
                dp = vel * dt
                new_vel = vel
            else:
                s, c = math.sin(om * dt), math.cos(om * dt)
                vx, vy = vel[:, 0], vel[:, 1]
                dp = torch.stack([(s * vx - (1 - c) * vy) / om, ((1 - c) * vx + s * vy) / om], -1)
                new_vel = torch.stack([c * vx - s * vy, s * vx + c * vy], -1)
            w = torch.randn(runs, 2, generator=gen, dtype=dtype, device=device) * accel_std
            pos = pos + dp + 0.5 * w * dt ** 2
            vel = new_vel + w * dt
        out_p.append(pos)
        out_v.append(vel)
    return _centre(torch.stack(out_p, 1)), torch.stack(out_v, 1)


#: the Liu scenarios' trajectory generators: ``conf/scenario/s1..s3.yaml`` and
#: ``task.scenario_params.s1..s3`` name them as ``_target_`` (``_partial_: true``: runs, steps,
#: random generator, dt, dtype are supplied at run time)
GENERATORS = {"s1": generate_s1, "s2": generate_s2, "s3": generate_s3}


def generator_target(name: str) -> str:
    """The ``_target_`` (import path) of scenario ``name``'s generator."""
    fn = GENERATORS[name]
    return f"{fn.__module__}.{fn.__name__}"


def sensor_field(runs: int, num_sensors: int, area: float, gen: torch.Generator,
                 dtype=torch.float64, device="cpu") -> Tensor:
    """Sensors uniform over the square ``[-area/2, area/2]^2``: ``(runs, S, 2)``."""
    u = torch.rand(runs, num_sensors, 2, generator=gen, dtype=dtype, device=device)
    return (u - 0.5) * area


def measure(truth: Tensor, sensors: Tensor, sensing_range: float, noise_std: Tensor,
            gen: torch.Generator):
    """Each sensor within range measures the position with i.i.d. N(0, sigma^2) noise per axis.

    Args:
        truth: ``(B, T, 2)``; sensors: ``(B, S, 2)``; noise_std: ``(B,)``.

    Returns:
        z: ``(B, S, T, 2)`` measurements (0 where not detected), avail: ``(B, S, T)`` bool.
    """
    d = torch.linalg.vector_norm(sensors[:, :, None, :] - truth[:, None, :, :], dim=-1)
    avail = d <= sensing_range
    e = torch.randn(avail.shape + (2,), generator=gen, dtype=truth.dtype, device=truth.device)
    z = truth[:, None] + noise_std.reshape(-1, 1, 1, 1) * e
    return torch.where(avail.unsqueeze(-1), z, torch.zeros_like(z)), avail
