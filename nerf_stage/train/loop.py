"""One training loop for every backbone: progress, the stage clock, the log, the divergence
check and the checkpoint cadence are written once here; a backbone hands the loop its
steps behind ``Steps`` (as nerfstudio's models hand callbacks to one trainer).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Protocol

import torch
from tqdm import tqdm

from palette_core.errors import InputError

from .checkpoint import CHECKPOINT
from .config import TrainConfig
from .schedule import next_iteration, stage_progress


class Steps(Protocol):
    """What a backbone does at the points of the loop, for its ``run`` (``run.RunBase``):

    - ``before(it)``: switch stage or refresh targets before iteration ``it``;
    - ``loss(it, progress)``: the loss of iteration ``it`` (``progress`` through its stage,
      ``schedule.stage_progress``) and the PSNR of its colours, before any update;
    - ``update(loss, it)``: the gradients of a finite ``loss`` and one optimiser step;
    - ``stage``: the stage's name for the log; ``extra()``: more fields for the log;
    - ``save(path)``: the checkpoint, with every state a resumed run needs to continue
      exactly as the uninterrupted run would.
    """

    run: object
    stage: str

    def before(self, it: int) -> None: ...

    def loss(self, it: int, progress: float) -> tuple[torch.Tensor, float]: ...

    def update(self, loss: torch.Tensor, it: int) -> None: ...

    def extra(self) -> dict: ...

    def save(self, path: Path) -> None: ...


def train_loop(config: TrainConfig, steps: Steps, rundir: Path, last: int, name: str,
               progress: bool = True) -> None:
    """Train ``steps.run`` from its recorded iteration to ``last``: a progress bar, the run's
    log (iteration, seconds, loss, PSNR, stage and the steps' ``extra``), the stages'
    clock (``schedule.next_iteration``), a checkpoint every ``config.checkpoint_every``
    iterations and at the end.

    Raises
    ------
    InputError
        If a loss is not finite (nothing of that step is applied or saved).
    """
    run = steps.run
    log, it = run.record.log, run.record.iteration
    bar = tqdm(desc=f"train {name}", initial=it, total=last, disable=not progress, unit="it")
    clock = time.perf_counter() - (log[-1]["seconds"] if log else 0.0)
    while it < last:
        steps.before(it)
        loss, psnr = steps.loss(it, stage_progress(config, it, log, last))
        if not torch.isfinite(loss):
            raise InputError(f"training diverged at iteration {it + 1} (the loss is not "
                             "finite): lower the learning rates or start afresh with another "
                             "seed")
        steps.update(loss, it)
        seconds, extra = time.perf_counter() - clock, steps.extra()
        log.append({"iteration": it + 1, "seconds": seconds, "loss": loss.item(), "psnr": psnr,
                    "stage": steps.stage, **extra})
        it = next_iteration(config, it + 1, seconds, last)
        run.record.iteration = it
        bar.update(it - bar.n)
        bar.set_postfix(stage=steps.stage, **extra, loss=f"{loss.item():.2e}",
                        psnr=f"{psnr:.2f}")
        if it % config.checkpoint_every == 0 or it == last:
            steps.save(rundir / CHECKPOINT)
    bar.close()
