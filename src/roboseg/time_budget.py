"""A training schedule that ends within ``trainer.max_time`` on a slower machine.

``trainer.max_time`` alone cuts a run where the time runs out: on a machine slower than the one
a recipe was tuned on, training then stops half-way down its cosine learning-rate schedule and
augmentation ramp, and the last validations never happen. :class:`FitScheduleToTime` measures
the seconds a training step and a validation take, and where ``trainer.max_steps`` would not fit
in ``trainer.max_time`` it shortens the whole schedule instead: the step count, the learning-rate
horizon (:attr:`roboseg.training.SegmentationModule.schedule_steps`), the augmentation ramp and
the validation interval (the same number of validations, the last at the final step). It never
lengthens a run beyond ``trainer.max_steps``; ``trainer.max_time`` stays the hard limit.
Measured in ``make train`` on an AVX2-only CPU (float32, ~0.55 s a step; 1800 steps do not fit
its 10.5 min guard): fitted runs end annealed and validated at their last step, with draped
validation IoU 0.54-0.67 against 0.61-0.63 cut, within the spread of runs (README).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Timer

log = logging.getLogger("roboseg.train")


@dataclass(frozen=True)
class Schedule:
    """Optimizer steps of a run and the interval (steps) between its validations."""

    steps: int
    val_every: int


def fitted_schedule(
    step: int,
    elapsed_s: float,
    budget_s: float,
    step_s: float,
    val_s: float,
    configured: Schedule,
    margin: float = 0.97,
) -> Schedule:
    """The schedule to follow from ``step`` on: ``configured`` where it ends within
    ``margin · budget_s`` seconds, else the longest one with as many validations, evenly spaced
    and the last at its final step, that does; a run that cannot fit ends at the next step.

    ``step``: steps done after ``elapsed_s`` seconds; ``step_s`` / ``val_s``: seconds a training
    step / a validation takes; validations still to come are counted at ``val_s`` each.
    """
    if min(step_s, budget_s) <= 0 or min(configured.steps, configured.val_every) < 1:
        raise ValueError(f"need step_s, budget_s > 0 and a schedule of >= 1 step; got "
                         f"step_s={step_s}, budget_s={budget_s}, {configured}")
    n_val = max(1, configured.steps // configured.val_every)

    def fits(schedule: Schedule) -> bool:
        vals_left = max(0, schedule.steps // schedule.val_every - step // schedule.val_every)
        left = (schedule.steps - step) * step_s + vals_left * val_s
        return elapsed_s + left <= margin * budget_s

    if fits(configured):
        return configured
    for val_every in range(configured.steps // n_val, 0, -1):
        schedule = Schedule(val_every * n_val, val_every)
        if schedule.steps <= step:
            break
        if fits(schedule):
            return schedule
    return Schedule(step + 1, step + 1)


class FitScheduleToTime(pl.Callback):
    """Shorten the schedule of a run that would not end within ``trainer.max_time``.

    After ``measure_after`` steps (the first ``skip`` ones not timed: loader start-up), and again
    after every validation (whose duration it then knows), it fits the run with
    :func:`fitted_schedule`, timing the steps since step ``skip`` (validations excluded), and
    applies the result: ``trainer.max_steps``, the module's learning-rate horizon
    (``schedule_steps``), the augmentation ramp (``augment.ramp_steps``, scaled in proportion)
    and the validation interval. A shorter fit is always applied; a longer one (the machine was
    busy while it measured) only if it adds at least ``lengthen_by`` of the steps, and never
    beyond ``trainer.max_steps``. Does nothing without a time limit (``trainer.max_time``) or
    when ``enabled`` is false. Fits are decided on rank zero and broadcast, so DDP ranks agree.
    """

    def __init__(
        self, enabled: bool = True, measure_after: int = 50, skip: int = 10,
        margin: float = 0.97, lengthen_by: float = 0.05,
    ) -> None:
        if skip < 0 or measure_after <= skip:
            raise ValueError(f"need 0 <= skip < measure_after, got {skip}, {measure_after}")
        self.enabled, self.measure_after, self.skip = enabled, measure_after, skip
        self.margin, self.lengthen_by = margin, lengthen_by
        self.configured: Schedule | None = None   # as configured: max_steps, val interval
        self.current: Schedule | None = None      # as fitted (None: never changed)
        self.fits: list[tuple[int, Schedule]] = []  # (step, schedule) of every change
        self.ramp_steps: int | None = None         # the augmentation ramp as configured
        self._mark: tuple[float, int, float] | None = None  # at step `skip`: time, step, val s
        self._val_total = 0.0                      # seconds spent in validations
        self._val_count = 0
        self._val_start: float | None = None

    # --- state ----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {"configured": None if self.configured is None else vars(self.configured),
                "current": None if self.current is None else vars(self.current),
                "ramp_steps": self.ramp_steps}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.configured = Schedule(**state_dict["configured"]) if state_dict.get(
            "configured") else None
        self.current = Schedule(**state_dict["current"]) if state_dict.get("current") else None
        self.ramp_steps = state_dict.get("ramp_steps")

    # --- hooks ----------------------------------------------------------------------------

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self._active(trainer):
            return
        if self.configured is None:
            interval = trainer.val_check_batch
            val_every = int(interval) if isinstance(interval, int | float) and math.isfinite(
                interval) else trainer.max_steps
            self.configured = Schedule(int(trainer.max_steps), max(1, val_every))
            augment = getattr(pl_module, "augment", None)
            self.ramp_steps = int(getattr(augment, "ramp_steps", 0) or 0)
        if self.current is not None:  # resumed: the fitted schedule holds on
            self._apply(trainer, pl_module, self.current)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        if not self._active(trainer):
            return
        step = trainer.global_step
        if self._mark is None and step >= self.skip:
            self._mark = (time.monotonic(), step, self._val_total)
        if step == self.measure_after:
            self._refit(trainer, pl_module)

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._active(trainer) and not trainer.sanity_checking:
            self._val_start = time.monotonic()

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._val_start is None or trainer.sanity_checking or not self._active(trainer):
            return
        self._val_total += time.monotonic() - self._val_start
        self._val_count += 1
        self._val_start = None
        if trainer.global_step > self.measure_after:
            self._refit(trainer, pl_module)

    # --- fitting --------------------------------------------------------------------------

    def _active(self, trainer: pl.Trainer) -> bool:
        return (self.enabled and trainer.max_steps > 0 and _timer(trainer) is not None
                and trainer.state.fn == "fit")

    def _refit(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        timer, configured, mark = _timer(trainer), self.configured, self._mark
        step = trainer.global_step
        if timer is None or configured is None or mark is None or step <= mark[1]:
            return
        # the mean since step `skip`: a window's own mean swings with the machine's load (0.56 to
        # 0.63 s a step between validations on an otherwise idle 2-core machine)
        step_s = (time.monotonic() - mark[0] - (self._val_total - mark[2])) / (step - mark[1])
        val_s = self._val_total / self._val_count if self._val_count else 0.0
        elapsed = timer.time_elapsed("train")
        budget = elapsed + (timer.time_remaining("train") or 0.0)
        if budget <= 0 or step_s <= 0:
            return
        schedule = fitted_schedule(step, elapsed, budget, step_s, val_s, configured, self.margin)
        schedule = Schedule(*trainer.strategy.broadcast(
            (schedule.steps, schedule.val_every), src=0))
        current = self.current or configured
        if not (schedule.steps < current.steps
                or schedule.steps >= current.steps * (1 + self.lengthen_by)):
            return
        log.log(logging.WARNING if self.current is None else logging.INFO,
                "at %.2f s a training step and %.1f s a validation, the schedule (learning rate, "
                "augmentation ramp, validations) ends at step %d of trainer.max_steps=%d to end "
                "within trainer.max_time (%.0f s)", step_s, val_s, schedule.steps,
                configured.steps, budget)
        self.current = schedule
        self.fits.append((step, schedule))
        self._apply(trainer, pl_module, schedule)

    def _apply(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
               schedule: Schedule) -> None:
        trainer.fit_loop.epoch_loop.max_steps = schedule.steps
        trainer.val_check_batch = schedule.val_every
        if hasattr(pl_module, "schedule_steps"):
            pl_module.schedule_steps = schedule.steps
        augment = getattr(pl_module, "augment", None)
        if augment is not None and self.ramp_steps and self.configured is not None:
            augment.ramp_steps = max(1, round(
                self.ramp_steps * schedule.steps / self.configured.steps))


def _timer(trainer: pl.Trainer) -> Timer | None:
    for callback in trainer.callbacks:
        if isinstance(callback, Timer) and callback.time_remaining() is not None:
            return callback
    return None
