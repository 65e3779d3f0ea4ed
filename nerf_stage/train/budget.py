"""Iterations planned for a wall-clock budget (``--minutes``), for every backbone: a short
probe of the run's own first stage times its iterations, and the run is planned
``HEADROOM`` times as long as that rate allows, so that the clock, not the iterations, ends
each stage (its rates then decayed by the clock: ``schedule.stage_progress``), and a run
given twenty minutes trains for twenty minutes (docs/decisions/0006-minutes.md).
"""

from __future__ import annotations

from dataclasses import replace

from .config import Strategy, TrainConfig

PROBE_ITERS = 40  # iterations of the probe that times the first stage
SPEED_UP = 2.0  # how much faster iterations run than the probe's (the occupancy grid prunes)
#: Iterations planned beyond the expected ones: every stage ends by the clock, so a plan
#: far longer than the budget costs nothing (a field's iterations speed up by up to ten
#: times once empty space is pruned).
HEADROOM = 10.0


def needs_plan(config: TrainConfig) -> bool:
    """Whether a fresh run of ``config`` plans its iterations (``planned``)."""
    return bool(config.minutes) and config.fill_minutes


def probe_config(config: TrainConfig) -> TrainConfig:
    """The probe: ``PROBE_ITERS`` iterations of ``config``'s first stage, without a clock."""
    return replace(config, strategy=Strategy.RGB, pretrain_iters=PROBE_ITERS,
                   finetune_iters=0, minutes=0.0, pretrain_minutes=0.0, fill_minutes=False,
                   checkpoint_every=PROBE_ITERS)


def probe_rate(log: list[dict]) -> float:
    """Iterations a second over the second half of the probe's ``log`` (past its warm-up)."""
    half = log[len(log) // 2:]
    return (len(half) - 1) / max(half[-1]["seconds"] - half[0]["seconds"], 1e-9)


def planned(config: TrainConfig, rate: float) -> TrainConfig:
    """``config`` with its iterations planned for its ``minutes`` at ``rate`` iterations a
    second: each stage ``HEADROOM`` times the iterations ``SPEED_UP`` times the rate fits in
    its share of the time (two-stage pretraining: ``pretrain_minutes``, or P / (P + F) of
    the budget), the shares kept."""
    share = (config.pretrain_minutes / config.minutes if config.pretrain_minutes else
             config.pretrain_iters / config.total_iters)
    two_stage = config.strategy == Strategy.TWO_STAGE
    share = share if two_stage else 1.0
    iterations = HEADROOM * SPEED_UP * 60 * config.minutes * rate
    return replace(config, pretrain_iters=max(1, round(iterations * share)),
                   finetune_iters=max(int(two_stage), round(iterations * (1 - share))),
                   pretrain_minutes=config.minutes * share if two_stage else 0.0,
                   fill_minutes=False)


def plans_like(planned_config: TrainConfig, config: TrainConfig) -> bool:
    """Whether ``planned_config`` (a checkpoint's) is a plan of ``config``: what
    ``--resume`` asks of a planned run."""
    if not needs_plan(config):
        return False
    return planned_config.trains_like(replace(
        config, pretrain_iters=planned_config.pretrain_iters,
        finetune_iters=planned_config.finetune_iters,
        pretrain_minutes=planned_config.pretrain_minutes, fill_minutes=False))
