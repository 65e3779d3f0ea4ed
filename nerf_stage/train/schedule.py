"""The stage clock and the learning rates that follow it, for every backbone.

A run trains in stages (two-stage: RGB pretraining, then the palette stage; one stage
otherwise). A stage ends when its iterations are done or, under ``--minutes`` and
``--pretrain-minutes``, when its share of the time is spent (``stage_deadline``,
``next_iteration``); how far a step is through its stage (``stage_progress``) is what the
learning rates decay by (``set_rates``) and what densification stops at, so that a stage
the clock ends decays as far as one its iterations end. docs/training.md.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Callable

from .config import Strategy, TrainConfig


def stage_progress(config: TrainConfig, it: int, log: list, last: int | None = None) -> float:
    """How far iteration ``it`` is through its stage, in [0, 1]: the share of the stage's
    iterations done (two-stage: pretraining, then fine-tuning up to ``last``, as
    ``next_iteration`` has them) or, under a wall-clock limit, the share of the stage's time
    spent by the run's ``log`` when that is more, so that a stage that the clock ends has
    its learning rates decayed as far as one that its iterations end."""
    last = config.total_iters if last is None else last
    pretraining = is_pretraining(config, it)
    two_stage = config.strategy == Strategy.TWO_STAGE
    start = config.pretrain_iters if two_stage and not pretraining else 0
    end = config.pretrain_iters if pretraining else last
    done = min((it - start) / max(1, end - start), 1.0)
    until = stage_deadline(config, pretraining, last)
    if until is None or not log:
        return done
    begin = 0.0  # fine-tuning begins when pretraining's last logged iteration ended
    stage = bisect_right(log, start, key=lambda entry: entry["iteration"]) if start else 0
    if stage:
        begin = log[stage - 1]["seconds"]
    return min(max(done, (log[-1]["seconds"] - begin) / max(until - begin, 1e-9)), 1.0)


def next_iteration(config: TrainConfig, it: int, seconds: float,
                   last: int | None = None) -> int:
    """The iteration after ``it`` iterations in ``seconds``: ``it``, or the next stage's
    first (two-stage fine-tuning; ``last``, by default ``config.total_iters``, for one stage
    or the last) once the stage has reached its ``stage_deadline``."""
    last = config.total_iters if last is None else last
    pretraining = is_pretraining(config, it)
    until = stage_deadline(config, pretraining, last)
    if until is None or seconds < until:
        return it
    return config.pretrain_iters if pretraining else last


def stage_deadline(config: TrainConfig, pretraining: bool, last: int | None = None
                   ) -> float | None:
    """Seconds from the run's start at which pretraining (or the stage after it, or the
    only one) ends under ``config.minutes`` and ``config.pretrain_minutes``; None: never."""
    if pretraining and config.pretrain_minutes:
        return 60 * config.pretrain_minutes
    if not config.minutes:
        return None
    last = config.total_iters if last is None else last
    return 60 * config.minutes * (config.pretrain_iters / last if pretraining else 1.0)


def is_pretraining(config: TrainConfig, it: int) -> bool:
    """Whether iteration ``it`` is in a two-stage run's RGB pretraining."""
    return config.strategy == Strategy.TWO_STAGE and it < config.pretrain_iters


def set_rates(optimisers: list, progress: float, start: Callable[[dict], float],
              final: Callable[[dict], float | None]) -> None:
    """Set each parameter group's rate to its ``start(group)`` rate times its ``final(group)``
    factor to the power ``progress`` (``stage_progress``): an exponential decay over the
    stage from its start rate to ``final`` times it; a group whose ``final`` is None keeps
    its rate."""
    for optimiser in optimisers:
        for group in optimiser.param_groups:
            factor = final(group)
            if factor is not None:
                group["lr"] = start(group) * factor ** progress
