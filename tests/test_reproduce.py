"""``python -m roboseg.reproduce``: the whole driver on a tiny study, its resume, its stages."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from roboseg.reproduce_report import at_a_glance, frame_errors_mm, md_table, portable
from roboseg.stages import Stages

ROOT = Path(__file__).resolve().parents[1]

#: every training run: whole 64² inputs, batch 2, one validation batch per step
SMALL_TRAIN = [
    "data.image_size=[64,64]", "augment.crop=null", "data.batch_size=2", "data.num_workers=0",
    "data.shuffle_buffer=8",
    "trainer.val_check_interval=1", "trainer.limit_val_batches=1",
    "trainer.num_sanity_val_steps=0", "trainer.enable_progress_bar=false",
]
REGISTER = [
    "cso.n_particles=32", "cso.iterations=2", "cso.width=24", "sdr.max_iterations=3",
    "prior.iterations=2", "prior.refresh_every=1", "width=64", "coarse_width=32",
]
MODELS = (
    "recipes.cpu=["
    "{name: m3, experiment: default, subset: full, overrides: ['trainer.max_steps=${steps}']},"
    "{name: m4, experiment: default, subset: full, overrides: ['model.in_channels=4',"
    " 'data.prior_probability=0.5', 'trainer.max_steps=${steps}']}]"
)
PAGE_SECTIONS = (
    "## At a glance", "## Study", "## Self-annotation quality",
    "## Segmentation (Table S4 columns)",
    "## Localisation of the draped test recording", "## Breathing motion (tracking demo)",
    "## Benchmarks", "## Run",
)


def _quoted(items: list[str]) -> str:
    return "[" + ",".join(f'"{x}"' for x in items) + "]"


def tiny_overrides(tmp: Path) -> list[str]:
    """A complete study of 12-frame 96×64 recordings, 2 training steps, a tiny swarm."""
    return [
        f"out={tmp / 'out'}", f"results={tmp / 'docs' / 'results.md'}",
        "frames=12", "width=96", "height=64", "steps=1", "lab.steps=1",
        "operating_room.width=null", "operating_room.height=null",
        "lab.recordings={train:1,val:1}", "operating_room.recordings={train:1,val:1,test:1}",
        "lab.in_training=true",  # the merge of lab and operating-room frames is checked below
        "register.configs=3", f"register.overrides={_quoted(REGISTER)}",
        f"train_overrides={_quoted(SMALL_TRAIN)}", f"lab.overrides={_quoted(SMALL_TRAIN)}",
        'annotate.overrides=["min_joint_speed=0.0"]', "track.frames=6", MODELS,
        "localise.cpu={sdr: m3, sdr_prior: m4}", "undraped.overrides=[]",
        "walkers.recordings=[or_train_00]", "walkers.people=1",
        "benches=[{name: echo, cmd: [python, -c, 'import os; print(\"figure 42.0 ms\");"
        " print(\"plot: \" + os.getcwd() + \"/bench/p.png\")']}]",
    ]


def _reproduce(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "roboseg.reproduce", *args], cwd=ROOT, capture_output=True,
        text=True, timeout=900,
    )


@pytest.mark.slow
def test_reproduce_tiny_study_then_resume(tmp_path: Path) -> None:
    proc = _reproduce(tiny_overrides(tmp_path))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = tmp_path / "out"
    n_stages = int(proc.stdout.split(" stages into ")[0].split()[-1])
    markers = sorted(p.name for p in out.glob(".*.done"))
    assert len(markers) == n_stages
    for stage in ("simulate_lab_train_00", "train_bootstrap", "export_bootstrap",
                  "register_undraped_or_test_00_robot_1", "annotate_full_or_val_00",
                  "annotation_quality", "train_m4", "export_m4", "evaluate", "evaluate_scales",
                  "register_draped_sdr_prior_robot_0", "track", "bench_echo"):
        assert f".{stage}.done" in markers
    assert f"[{n_stages}/{n_stages}" in proc.stdout and "total time:" in proc.stdout

    # the merged, self-annotated dataset and the annotation quality against the simulator
    # (with the lab's training recording, calibrated by its own /tf_static: lab.in_training)
    manifest = json.loads((out / "annotated" / "full" / "manifest.json").read_text())
    assert [(r["file"], r["split"], r["calibration"]) for r in manifest["recordings"]] == [
        ("or_train_00.mcap", "train", "file"), ("or_val_00.mcap", "val", "file"),
        ("or_test_00.mcap", "test", "file"), ("lab_train_00.mcap", "train", "tf_static")]
    assert all((out / "annotated" / "full" / r["file"]).is_file()
               for r in manifest["recordings"])
    assert manifest["totals"]["frames_kept"] == sum(
        r["frames_kept"] for r in manifest["recordings"])
    quality = json.loads((out / "metrics" / "annotation.json").read_text())
    assert len(quality["rows"]) == 3 and len(quality["rows"][2]["registration"]) == 2
    for row in quality["rows"]:
        assert 0.0 <= row["annotation"]["iou_mean"] <= 1.0
    # the same recording with someone walking through the view, beside the one without
    walk = json.loads((out / "metrics" / "walkers.json").read_text())
    assert [(r["recording"], r["people_walking"]) for r in walk["rows"]] == [
        ("or_train_00", 0), ("or_train_00_walkers", 1)]
    assert all(r["tool_median_mm"] >= 0 for r in walk["rows"])

    page = (tmp_path / "docs" / "results.md").read_text()
    for section in PAGE_SECTIONS:
        assert section in page
    assert "### People walking through the view" in page and "| or_train_00_walkers | 1 |" in page
    assert "comes from simulated recordings" in page and "SAM 2" in page
    assert "and the lab bootstrap's training recordings (`lab.in_training`)" in page
    assert "figure 42.0 ms" in page and "logical cores" in page
    # each model's steps as trained / trainer.max_steps (steps=1 in the tiny study)
    assert "| m3 | default | `trainer.max_steps=1` | 1/1 |" in page
    # the IoU table again at the draped registrations' scales, which the page names
    assert "segmented at 1.25, 1.5, 2 times the model's input size" in page
    assert "`model_scales=[1.25,1.5,2.0]`" in page
    assert "plot: bench/p.png" in page  # what a bench prints names paths from the project root
    figures = tmp_path / "docs" / "results"
    for name in ("localisation.png", "breathing.png", "qualitative_m3.png"):
        assert (figures / name).is_file() and f"results/{name}" in page

    again = _reproduce(tiny_overrides(tmp_path))
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("done already, skipped") == n_stages
    assert "] $ " not in again.stdout
    assert f"(0 of {n_stages} stages ran)" in again.stdout


def test_stages_tolerant_failure_is_recorded_and_skipped(tmp_path: Path) -> None:
    stages = Stages(tmp_path, total=3, runner="fork")
    assert stages.run("ok", [sys.executable, "-c", "print('hello')"])
    assert (tmp_path / "logs" / "ok.stdout").read_text() == "hello\n"
    assert stages.run("bad", [sys.executable, "-c", "raise SystemExit(3)"], tolerant=True)
    assert stages.status("bad")[1] == 3
    assert not stages.run("bad", [sys.executable, "-c", "raise SystemExit(3)"], tolerant=True)
    with pytest.raises(SystemExit, match="exit status 3"):
        stages.run("strict", [sys.executable, "-c", "raise SystemExit(3)"])
    assert stages.status("strict") == (None, None)


def test_stages_side_by_side_overlap_and_count_once_in_wall_time(tmp_path: Path) -> None:
    from roboseg.stages import Step

    stages = Stages(tmp_path, total=3, runner="fork")
    nap = "import time; time.sleep(1.5); print('{}')"
    steps = [
        Step("a", [sys.executable, "-c", nap.format("a")], parallel=True),
        Step("b", [sys.executable, "-c", nap.format("b")], parallel=True),
        Step("c", [sys.executable, "-c", "raise SystemExit(2)"], tolerant=True, parallel=True),
    ]
    assert stages.run_side_by_side(steps, jobs=2) == 3
    assert (tmp_path / "logs" / "b.stdout").read_text() == "b\n"
    assert stages.status("c")[1] == 2
    (a0, a1), (b0, b1) = stages.interval("a"), stages.interval("b")
    assert a0 < b1 and b0 < a1  # they overlapped
    stage_sum = sum(stages.status(n)[0] for n in "abc")
    wall = stages.wall_seconds(["a", "b", "c"])
    assert 1.5 <= wall < stage_sum - 1.0, (wall, stage_sum)
    assert stages.run_side_by_side(steps, jobs=2) == 0  # all done: skipped
    with pytest.raises(SystemExit, match="exit status 4"):
        stages.run_side_by_side(
            [Step("d", [sys.executable, "-c", "raise SystemExit(4)"], parallel=True),
             Step("e", [sys.executable, "-c", "print('e')"], parallel=True)], jobs=2,
        )
    assert stages.status("e")[1] == 0  # the other one still finished


def test_stages_after_an_unfinished_one_are_redone(tmp_path: Path) -> None:
    """Groups [a], [b, c] (side by side), [d], [e]: with b's marker gone, c (independent of b)
    stays done while d and e, which may read b's output, lose their markers; with nothing
    unfinished nothing is removed."""
    from roboseg.reproduce import plan_groups
    from roboseg.stages import Step

    plan = [Step("a"), Step("b", parallel=True), Step("c", parallel=True), Step("d"), Step("e")]
    groups = plan_groups(plan)
    assert groups == [["a"], ["b", "c"], ["d"], ["e"]]
    stages = Stages(tmp_path, total=5, runner="process")
    for name in "abcde":
        stages.marker(name).write_text("1.0 s\n")
    assert stages.redo_after_pending(groups) == []
    stages.marker("b").unlink()
    assert stages.redo_after_pending(groups) == ["d", "e"]
    assert [n for n in "abcde" if stages.marker(n).exists()] == ["a", "c"]


def test_stages_forked_function(tmp_path: Path) -> None:
    stages = Stages(tmp_path, total=2, runner="fork")
    target = tmp_path / "written.txt"

    def work() -> None:
        print("from the child")
        target.write_text("done")

    assert stages.run("work", ["work"], fn=work)
    assert target.read_text() == "done"
    assert "from the child" in (tmp_path / "logs" / "work.stdout").read_text()

    def fail() -> None:
        raise RuntimeError("boom")

    with pytest.raises(SystemExit, match="exit status 1"):
        stages.run("fail", ["fail"], fn=fail)
    assert "RuntimeError: boom" in (tmp_path / "logs" / "fail.log").read_text()


def test_frame_errors_are_the_offset_of_a_translated_estimate(default_robot) -> None:
    q = np.zeros((2, default_robot.dof))
    T_true = np.eye(4)
    T_true[:3, 3] = [0.1, -0.2, 1.5]
    T_est = T_true.copy()
    T_est[:3, 3] += [0.003, 0.0, -0.004]  # 5 mm
    err = frame_errors_mm(default_robot, q, T_est, T_true)
    assert err.shape == (2, len(default_robot.frame_names))
    np.testing.assert_allclose(err, 5.0, atol=1e-6)
    assert np.all(frame_errors_mm(default_robot, q, T_true, T_true) < 1e-9)


def test_md_table() -> None:
    assert md_table(["a", "b"], [[1, "x"]]) == "| a | b |\n|---|---|\n| 1 | x |\n"


def test_at_a_glance_counts_failures_convergence_and_annotation_quality() -> None:
    stages = [("simulate", 60.0, 0), ("register_a", 90.0, 1), ("register_b", 30.0, 0),
              ("bench", None, None)]
    annotation = {"rows": [
        {"annotation": {"iou_mean": 0.9},
         "registration": [{"converged": True, "tool_median_mm": 4.0}]},
        {"annotation": {"iou_mean": 0.5},
         "registration": [{"converged": False, "tool_median_mm": 2.0},
                          {"converged": True, "tool_median_mm": 10.5}]},
    ]}
    localisation = {"rows": [{"converged": True, "tool_median_mm": 12.5},
                             {"converged": False, "tool_median_mm": 3.0}]}
    lines = at_a_glance(stages, "0.812", annotation, localisation)
    assert lines[0] == ("- stages: 2 of 4 ok, 1 failed (register_a), 1 not run; "
                        "3.0 min of stage time in all")
    assert lines[1].endswith("validation IoU 0.812")
    # within 10 mm counts converged estimates only (the 2.0 mm one did not converge)
    assert lines[2] == ("- undraped registrations converged: 2 of 3, 1 within 10 mm; "
                        "self-annotated masks vs simulator: mean IoU 0.700 over 2 recordings")
    assert lines[3] == ("- draped test registrations converged: 1 of 2, 0 within 10 mm; median "
                        "tool-centre error 3.0–12.5 mm")
    assert len(at_a_glance(stages[:1], "-", None, None)) == 2
    timed = at_a_glance(stages, "-", None, None, wall_seconds=150.0)
    assert timed[0].endswith("; 2.5 min wall clock; 3.0 min of stage time in all")


def test_portable_commands_name_python_and_relative_paths(tmp_path: Path) -> None:
    cmd = f"/opt/venv/bin/python -m bench.x --model {tmp_path}/models/a.onnx --out /elsewhere/b"
    assert portable(cmd, tmp_path, python="/opt/venv/bin/python") == (
        "python -m bench.x --model models/a.onnx --out /elsewhere/b")


def test_plan_study_gives_every_recording_its_own_seed() -> None:
    from omegaconf import OmegaConf

    from roboseg.reproduce import plan_study

    cfg = OmegaConf.load(ROOT / "conf" / "reproduce.yaml")
    cfg.lab.recordings = {"train": 16, "val": 2}
    lab, study = plan_study(cfg)
    assert [r.stem for r in lab][:2] == ["lab_train_00", "lab_train_01"]
    assert len(lab) == 18 and len({r.seed for r in lab + study}) == 18 + len(study)
    cfg.lab.recordings = {"train": 101, "val": 1}  # lab_train_100 lands on lab_val_00's seed
    with pytest.raises(SystemExit, match="lab_train_100 and lab_val_00 would share seed 11000"):
        plan_study(cfg)
    cfg.lab.recordings = {"train": 2, "val": 1}
    cfg.operating_room.recordings = {"train": 12, "val": 1, "test": 1}
    _, study = plan_study(cfg)
    seeds = {r.stem: r.seed for r in study}
    assert [seeds[f"or_train_{i:02d}"] for i in (0, 1, 9, 10, 11)] == [0, 100, 900, 50, 150]
    assert seeds["or_val_00"] == 1000 and seeds["or_test_00"] == 2000
    cfg.operating_room.recordings = {"train": 21, "val": 1, "test": 1}  # 21st: seed 100 again
    with pytest.raises(SystemExit, match="or_train_01 and or_train_20 would share seed 100"):
        plan_study(cfg)


def test_walkers_repeat_study_recordings_with_people_walking(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from roboseg.reproduce import Layout, build_plan, model_specs, plan_study, plan_walkers

    cfg = OmegaConf.load(ROOT / "conf" / "reproduce.yaml")
    cfg.walkers = {"recordings": ["or_train_01"], "people": 2}
    lab, study = plan_study(cfg)
    walkers = plan_walkers(cfg, study)
    alone = next(r for r in study if r.stem == "or_train_01")
    assert [(r.stem, r.seed, r.split) for r in walkers] == [
        ("or_train_01_walkers", alone.seed, alone.split)]  # same room, placement and motion
    layout = Layout(tmp_path, tmp_path / "page.md", lab, study, model_specs(cfg), walkers)
    plan = {step.name: step for step in build_plan(cfg, layout)}
    sim = plan["simulate_or_train_01_walkers"].argv
    assert "walkers=2" in sim and f"seed={alone.seed}" in sim and "site=1" in sim
    assert {"camera.width=960", "camera.height=540"} <= set(sim)  # the room's image size
    reg = plan["register_undraped_or_train_01_walkers_robot_0"]
    assert reg.parallel and "phase=undraped" in reg.argv
    assert "walkers_quality" in plan
    assert not any("or_train_01_walkers" in n for n in plan if n.startswith("annotate_"))
    cfg.walkers = {"recordings": ["or_train_99"], "people": 2}
    with pytest.raises(SystemExit, match="walkers.recordings: or_train_99 is not an"):
        plan_walkers(cfg, study)
    cfg.walkers = {"recordings": [], "people": 0}
    assert plan_walkers(cfg, study) == []


def test_lab_recordings_fold_into_one_row_per_split() -> None:
    from omegaconf import OmegaConf

    from roboseg.reproduce import plan_study
    from roboseg.reproduce_report import lab_rows

    cfg = OmegaConf.load(ROOT / "conf" / "reproduce.yaml")
    cfg.lab.recordings = {"train": 3, "val": 1}
    lab, _ = plan_study(cfg)
    rows = lab_rows(lab)
    assert [row[2] for row in rows] == ["train", "val"]
    train, val = rows
    assert train[0] == "lab_train_00 … lab_train_02 (3)" and train[3] == "1"
    assert train[4] == f"{lab[0].seed} … {lab[2].seed}"
    assert val[0] == "lab_val_00 (1)" and val[4] == str(lab[3].seed)


@pytest.mark.parametrize("segmentor", ["model", "motion"])
def test_undraped_segmentor_chooses_the_bootstrap_or_none(
    tmp_path: Path, segmentor: str, caplog: pytest.LogCaptureFixture
) -> None:
    from omegaconf import OmegaConf

    from roboseg.reproduce import (
        Layout,
        build_plan,
        lab_in_training,
        model_init,
        model_specs,
        plan_study,
    )

    cfg = OmegaConf.load(ROOT / "conf" / "reproduce.yaml")
    cfg.undraped.segmentor = segmentor
    cfg.undraped.overrides = ["self_training.rounds=1"]
    lab, study = plan_study(cfg)
    layout = Layout(tmp_path, tmp_path / "page.md", lab, study, model_specs(cfg))
    plan = {step.name: step for step in build_plan(cfg, layout)}
    bootstrap = [n for n in plan if "lab" in n or "bootstrap" in n]
    argv = plan["register_undraped_or_test_00_robot_1"].argv
    assert argv[-1] == "self_training.rounds=1"
    draped = plan["register_draped_sdr_robot_0"].argv
    assert f"model={layout.onnx(cfg.localise.cpu.sdr)}" in draped
    # the stereo disparity term holds the draped fits' distance (the undraped ones' is set in
    # undraped.overrides, replaced by this test's); the far test robots are segmented larger
    assert draped[-2:] == ["sdr.disparity_weight=1.0", "model_scales=[1.25,1.5,2.0]"]
    assert not any(a.startswith(("sdr.disparity_weight", "model_scales")) for a in argv)
    # the models are evaluated at the input size and at the draped registrations' scales
    assert "scales=[1.25,1.5,2.0]" in plan["evaluate_scales"].argv
    assert "out=" + str(tmp_path / "eval_scales") in plan["evaluate_scales"].argv
    assert not any(a.startswith("scales=") for a in plan["evaluate"].argv)
    # the operating-room recordings are sessions of one site; lab recordings random rooms
    assert "site=1" in plan["simulate_or_val_00"].argv
    # the operating room at its own size (960×540), the lab at every recording's (480×270)
    assert {"camera.width=960", "camera.height=540"} <= set(plan["simulate_or_val_00"].argv)
    if segmentor == "model":
        assert "train_bootstrap" in bootstrap and "simulate_lab_train_00" in bootstrap
        assert not any(a.startswith("site=") for a in plan["simulate_lab_train_00"].argv)
        assert {"camera.width=480", "camera.height=270"} <= set(plan["simulate_lab_train_00"].argv)
        assert f"model={layout.bootstrap_onnx}" in argv and "segmentor=motion" not in argv
        # the recipe's models start from the bootstrap's weights (model_init.cpu=bootstrap)
        start = f"model.weights_path={layout.bootstrap / 'model.ckpt'}"
        assert all(start in plan[f"train_{m.name}"].argv for m in layout.models)
    else:  # no lab rig, no model: the registrations name the segmentor, models start random
        assert bootstrap == []
        assert "segmentor=motion" in argv and not any(a.startswith("model=") for a in argv)
        assert not any("weights_path" in a for m in layout.models
                       for a in plan[f"train_{m.name}"].argv)
        # the fallback is warned of once, where the plan is made; the page asks quietly
        assert sum("start from scratch" in r.getMessage() for r in caplog.records) == 1
        caplog.clear()
        assert model_init(cfg, warn=False) == "scratch" and not caplog.records
    # the models learn from the lab's recordings only if asked and there is a lab stage
    assert not lab_in_training(cfg)  # the default: the operating room's sessions alone
    cfg.lab.in_training = True
    assert lab_in_training(cfg) == (segmentor == "model")
    cfg.undraped.segmentor = "prompt"
    with pytest.raises(SystemExit, match="undraped.segmentor=prompt: not one of model, motion"):
        build_plan(cfg, layout)


def test_operating_room_size_falls_back_to_every_recordings_size(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from roboseg.reproduce import Layout, build_plan, model_specs, operating_room_size, plan_study

    cfg = OmegaConf.load(ROOT / "conf" / "reproduce.yaml")
    assert operating_room_size(cfg) == (960, 540)  # the default: the room's own size
    cfg.operating_room.width = None
    cfg.operating_room.height = None
    assert operating_room_size(cfg) == (480, 270)  # null: every recording's size
    cfg.operating_room.width = 960
    cfg.operating_room.height = 540
    lab, study = plan_study(cfg)
    layout = Layout(tmp_path, tmp_path / "page.md", lab, study, model_specs(cfg))
    plan = {step.name: step for step in build_plan(cfg, layout)}
    assert {"camera.width=960", "camera.height=540"} <= set(plan["simulate_or_test_00"].argv)
    assert {"camera.width=480", "camera.height=270"} <= set(plan["simulate_lab_val_00"].argv)
    # the models' localisation bench meets them in their own room, at its image size
    bench = plan["bench_localisation_models"].argv
    assert bench[bench.index("--site") + 1] == "1"
    assert bench[bench.index("--sim-width") + 1 :][:3] == ["960", "--sim-height", "540"]
    assert str(layout.onnx(str(cfg.localise.cpu.sdr))) in bench
    # what it writes stays in the run's folder, beside the quick bench's
    assert bench[bench.index("--out") + 1] == str(tmp_path / "bench" / "localisation_models")
    quick = plan["bench_localisation"].argv
    assert quick[quick.index("--out") + 1] == str(tmp_path / "bench" / "localisation")
    cfg.operating_room.site = None
    plan = {step.name: step for step in build_plan(cfg, layout)}
    bench = plan["bench_localisation_models"].argv
    assert bench[bench.index("--site") + 1] == "none"
    cfg.operating_room.height = 8
    with pytest.raises(SystemExit, match="operating_room.width / height must be >= 16 px"):
        operating_room_size(cfg)


def test_masks_of_names_the_kind_of_self_training_rounds() -> None:
    from roboseg.reproduce_report import _masks_of

    reg = {"segmentor": "model", "self_training_rounds": 3, "self_training_kept": 2}
    assert _masks_of({**reg, "self_training_masks": "grabcut"}) == "model + GrabCut 3, kept 2"
    assert _masks_of({**reg, "self_training_masks": "self_trained"}) == (
        "model + self-training 3, kept 2")
    assert _masks_of({"segmentor": "motion", "self_training_rounds": 0}) == "motion"


def test_registration_error_scores_every_self_training_round(
    tmp_path: Path, default_robot
) -> None:
    """Each round's estimate in pose.yaml is scored against /tf_static like the kept one; the
    page cell lists them in order with the kept round in bold."""
    import yaml

    from roboseg.recording import RecordingReader
    from roboseg.reproduce_report import _estimate_cells, registration_error
    from roboseg.sim import SimConfig, simulate_recording

    path = tmp_path / "tiny.mcap"
    simulate_recording(SimConfig(frames=6, seed=3, width=96, height=64, undraped_fraction=0.5),
                       path)
    with RecordingReader(path) as r:
        T_true = r.lookup(r.camera_infos("left").frame_id,
                          f"robot_0/{default_robot.root_link}")
    off = T_true.copy()
    off[:3, 3] += [0.0, 0.012, 0.0]  # 12 mm
    rounds = [{"round": 0, "T_cam_base": off.tolist(), "kept": False},
              {"round": 1, "failed": "no masks", "kept": False},
              {"round": 2, "T_cam_base": T_true.tolist(), "kept": True}]
    pose = tmp_path / "pose.yaml"
    pose.write_text(yaml.safe_dump({"T_cam_base": T_true.tolist(), "robot": "robot_0",
                                    "converged": True, "self_training": rounds}))
    err = registration_error(pose, path, default_robot, "undraped")
    by_round = err["tool_median_mm_by_round"]
    assert by_round[1] is None
    np.testing.assert_allclose([by_round[0], by_round[2]], [12.0, 0.0], atol=1e-6)
    assert err["tool_median_mm"] == pytest.approx(0.0, abs=1e-6)
    assert err["self_training_kept"] == 2
    assert _estimate_cells(err)[-1] == "12.0 → - → **0.0**"
    assert _estimate_cells({**err, "tool_median_mm_by_round": [3.0]})[-1] == "–"


def test_rounds_plot_draws_registrations_that_ran_rounds(tmp_path: Path) -> None:
    from roboseg.reproduce_report import rounds_plot

    one = {"label": "a robot_0", "tool_median_mm_by_round": [170.0, 52.8, None, 10.2],
           "self_training_kept": 3}
    assert rounds_plot([{**one, "tool_median_mm_by_round": [3.0]}], tmp_path / "x.png") is None
    png = rounds_plot([one, {**one, "label": "b", "tool_median_mm_by_round": []}],
                      tmp_path / "r.png")
    assert png == tmp_path / "r.png" and png.stat().st_size > 1000
