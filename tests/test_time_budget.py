"""The schedule fitted to ``trainer.max_time`` (roboseg.time_budget)."""

from __future__ import annotations

import time
from datetime import timedelta

import lightning.pytorch as pl
import pytest
import torch
from torch.utils.data import DataLoader, IterableDataset

from roboseg.time_budget import FitScheduleToTime, Schedule, fitted_schedule


def test_a_schedule_that_fits_is_kept() -> None:
    # 25 s + 1750 steps x 0.5 s + 6 validations x 10 s = 960 s <= 0.97 x 1000 s
    assert fitted_schedule(50, 25.0, 1000.0, 0.5, 10.0, Schedule(1800, 300)) == Schedule(1800, 300)


def test_a_schedule_too_long_is_shortened_with_as_many_validations() -> None:
    # 30 + (6v - 50) 0.55 + 6 x 10 <= 0.97 x 630 = 611.1  <=>  v <= 166.2
    assert fitted_schedule(50, 30.0, 630.0, 0.55, 10.0, Schedule(1800, 300)) == Schedule(996, 166)


def test_validations_already_run_are_not_counted_again() -> None:
    # at step 600: 400 + (6v - 600) 0.5 + (6 - 600 // v) 10 <= 700  <=>  v <= 190
    assert fitted_schedule(600, 400.0, 700.0, 0.5, 10.0, Schedule(1800, 300),
                           margin=1.0) == Schedule(1140, 190)


def test_a_run_out_of_time_ends_at_the_next_step() -> None:
    assert fitted_schedule(120, 700.0, 630.0, 0.5, 10.0, Schedule(1800, 300)) == Schedule(121, 121)


@pytest.mark.parametrize(("step_s", "budget_s", "configured"), [
    (0.0, 10.0, Schedule(10, 5)), (1.0, 0.0, Schedule(10, 5)), (1.0, 10.0, Schedule(0, 1))])
def test_bad_figures_are_refused(step_s: float, budget_s: float, configured: Schedule) -> None:
    with pytest.raises(ValueError, match="step_s"):
        fitted_schedule(0, 0.0, budget_s, step_s, 0.0, configured)


def test_the_state_survives_a_checkpoint() -> None:
    callback = FitScheduleToTime()
    callback.configured, callback.current, callback.ramp_steps = (
        Schedule(1800, 300), Schedule(996, 166), 1800)
    restored = FitScheduleToTime()
    restored.load_state_dict(callback.state_dict())
    assert (restored.configured, restored.current, restored.ramp_steps) == (
        Schedule(1800, 300), Schedule(996, 166), 1800)


# --- in a Trainer -----------------------------------------------------------------------------


class _Endless(IterableDataset):
    def __iter__(self):  # noqa: ANN204
        g = torch.Generator().manual_seed(0)
        while True:
            yield torch.randn(4, generator=g)


class _Ramp:
    ramp_steps = 1000


class _SlowModule(pl.LightningModule):
    """Training steps of ~``step_s`` seconds; records where validations ran."""

    def __init__(self, step_s: float, busy_until: int = 0, busy_s: float = 0.0) -> None:
        super().__init__()
        self.layer = torch.nn.Linear(4, 1)
        self.step_s, self.busy_until, self.busy_s = step_s, busy_until, busy_s
        self.schedule_steps: int | None = 1000
        self.augment = _Ramp()
        self.validated_at: list[int] = []

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        time.sleep(self.busy_s if self.global_step < self.busy_until else self.step_s)
        return self.layer(batch).pow(2).mean()

    def validation_step(self, batch: torch.Tensor, batch_idx: int) -> None:
        if batch_idx == 0 and not self.trainer.sanity_checking:
            self.validated_at.append(self.global_step)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.01)


def _fit(module: _SlowModule, callback: FitScheduleToTime, max_time: timedelta | None
         ) -> pl.Trainer:
    pl.seed_everything(0)
    trainer = pl.Trainer(
        accelerator="cpu", max_steps=1000, max_time=max_time, val_check_interval=100,
        check_val_every_n_epoch=None, limit_val_batches=1, num_sanity_val_steps=0,
        callbacks=[callback], logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False)
    loader = DataLoader(_Endless(), batch_size=2)
    trainer.fit(module, train_dataloaders=loader, val_dataloaders=DataLoader(_Endless(),
                                                                            batch_size=2))
    return trainer


def test_a_slow_run_ends_its_shortened_schedule_in_time() -> None:
    module = _SlowModule(step_s=0.03)
    callback = FitScheduleToTime(measure_after=8, skip=2, margin=0.6)
    trainer = _fit(module, callback, timedelta(seconds=4))
    steps = trainer.global_step
    assert callback.current is not None and 8 < steps < 1000
    # the schedule's end was reached, not cut by the time limit, and everything follows it
    assert steps == trainer.max_steps == callback.current.steps == module.schedule_steps
    assert module.augment.ramp_steps == steps  # ramp over 1000 of 1000 steps → over all of them
    # as many validations as configured (10), the last at the final step
    assert module.validated_at[-1] == steps
    assert steps // callback.current.val_every == 10


@pytest.mark.parametrize(("enabled", "max_time"), [(False, timedelta(seconds=1)), (True, None)])
def test_nothing_is_fitted_when_disabled_or_without_a_time_limit(
        enabled: bool, max_time: timedelta | None) -> None:
    module = _SlowModule(step_s=0.0)
    callback = FitScheduleToTime(enabled=enabled, measure_after=8, skip=2)
    trainer = _fit(module, callback, max_time)
    assert callback.current is None and module.schedule_steps == 1000
    assert module.augment.ramp_steps == 1000
    if max_time is None:
        assert trainer.global_step == 1000


def test_a_fit_measured_on_a_busy_machine_is_lengthened_again() -> None:
    # steps take 0.1 s until step 10 (another job), then 0.01 s: the first fit, at step 5, is
    # too short for the rest of the run and later ones lengthen it
    module = _SlowModule(step_s=0.01, busy_until=10, busy_s=0.1)
    callback = FitScheduleToTime(measure_after=5, skip=1, margin=0.6)
    trainer = _fit(module, callback, timedelta(seconds=6))
    first, last = callback.fits[0][1], callback.fits[-1][1]
    assert first.steps < 60 and last.steps > 2 * first.steps
    assert trainer.global_step == last.steps == module.schedule_steps
    assert module.validated_at[-1] == last.steps
