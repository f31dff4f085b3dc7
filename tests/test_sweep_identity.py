"""The study schema fails on unknown keys naming file and key; a job's identity survives a new config key with its
old default and goes stale when a value changes; the recorder a training job loads imports nothing heavy."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import open_dict

from nvs.core.errors import UserError
from nvs.sweep import jobs as sweep_jobs
from nvs.sweep.jobs import JOB_RECORD, Status, config_changes, config_digest, plan, prepare_job_dir
from nvs.sweep.study import load_study

REPO = Path(__file__).resolve().parents[1]
STUDY = {"name": "ident", "seeds": [0], "size": 64, "steps": 10,
         "rows": [{"name": "full", "experiment": "nvs_chairs"},
                  {"name": "copy", "reference": "copy_source", "data": "chairs"}]}


def _write(tmp_path: Path, study: dict) -> Path:
    path = tmp_path / "ident.yaml"
    path.write_text(json.dumps(study))
    return path


# -- the schema ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad, where", [
    ({"colour": "red"}, ":1: unknown key 'colour'; expected one of ["),
    ({"rows": [{"name": "a", "colour": 1}]}, ":1: rows[0]: unknown key 'colour'; expected one of ["),
    ({"rows": [{"name": "a"}, {"name": "b", "lable": "x", "runn": "y"}]}, ":1: rows[1]: unknown keys 'lable', 'runn'"),
    ({"size": "big"}, ":1: size must be an integer, got 'big'"),
    ({"rows": [{"name": "a", "paper": {"l1": "low"}}]}, ":1: rows[0].paper.l1 must be a number, got 'low'"),
    ({"rows": [{"name": "a", "overrides": "model/skips=none"}]}, ":1: rows[0].overrides must be a list of strings"),
    ({"rows": [{"label": "no name"}]}, ":1: rows[0]: 'name' is missing"),
    ({"steps": None}, ": 'steps' is missing"),
    ({"group_by": "model"}, ":1: group_by must be one of ['data'] or null, got 'model'"),
])
def test_a_bad_key_is_one_error_naming_the_file_and_the_key(tmp_path, bad, where):
    path = _write(tmp_path, {**STUDY, **bad})  # JSON: one line
    with pytest.raises(UserError) as err:
        load_study(path)
    assert str(err.value).startswith(f"{path}{where}"), str(err.value)
    assert "\n" not in str(err.value)


def test_the_error_names_the_line_of_the_key(tmp_path):
    path = tmp_path / "lines.yaml"
    path.write_text("size: 64\nsteps: 10\nrows:\n  - name: a\n  - name: b\n    oracle: maybe\n"
                    "  - name: c\n\n    colour: red\n")
    with pytest.raises(UserError, match=rf"^{path}:6: rows\[1\]\.oracle must be true or false, got 'maybe'$"):
        load_study(path)
    path.write_text(path.read_text().replace("oracle: maybe", "oracle: true"))
    with pytest.raises(UserError, match=rf"^{path}:9: rows\[2\]: unknown key 'colour'"):
        load_study(path)


def test_the_schema_keeps_the_defaults_of_the_study_format(tmp_path):
    study = load_study(_write(tmp_path, {"size": 64, "steps": 10, "seeds": 3, "rows": [{"name": "a"}]}))
    assert study.name == "ident" and study.title == "ident" and study.seeds == (0, 1, 2)
    assert study.metrics[:2] == ("l1", "ssim_paper") and study.table == "metrics" and study.group_by is None
    row = study.rows[0]
    assert (row.label, row.run, row.overrides, row.paper, row.oracle, row.kind) == ("a", "a", (), {}, False, "train")


# -- identity ------------------------------------------------------------------------------------------------------
def _finished(tmp_path: Path):
    """The study planned and every job given a result (as if it had run with the config of today's conf/)."""
    study = load_study(_write(tmp_path, STUDY))
    root = tmp_path / "runs"
    for job in plan(study, root):
        prepare_job_dir(job, root)
        (job.dir / "metrics.json").write_text(json.dumps({"data": "chairs", "test": {"l1": 0.1}}))
    return study, root


def _conf_changes(monkeypatch, change) -> None:
    """As if a file in conf/ had changed: every composed config goes through ``change`` first."""
    compose = sweep_jobs.compose

    def changed(name, overrides):
        cfg = compose(name, overrides)
        with open_dict(cfg):
            change(cfg)
        return cfg

    monkeypatch.setattr(sweep_jobs, "compose", changed)


def test_a_new_config_key_with_its_old_default_keeps_finished_jobs_done(tmp_path, monkeypatch):
    study, root = _finished(tmp_path)
    before = {j.row.name: (j.key, j.digest) for j in plan(study, root)}

    def add_setting(cfg):
        cfg.model.new_switch = False          # a new switch at the behaviour the job was trained with
        cfg.data.new_group = {"a": 1}         # a plain new mapping of settings

    _conf_changes(monkeypatch, add_setting)
    jobs = plan(study, root)
    assert [j.status for j in jobs] == [Status.DONE, Status.DONE]
    for j in jobs:
        assert j.key == before[j.row.name][0]        # the key is made of overrides, not of conf/
        assert j.digest != before[j.row.name][1]     # the config did change: only the rule keeps the job
    assert sweep_jobs.to_launch(jobs) == []


def test_a_changed_value_of_an_existing_key_makes_the_job_stale(tmp_path, monkeypatch):
    study, root = _finished(tmp_path)
    _conf_changes(monkeypatch, lambda cfg: setattr(cfg.data, "max_delta_azimuth", 123))
    jobs = {j.row.name: j for j in plan(study, root)}
    assert jobs["full"].status == Status.STALE and jobs["copy"].status == Status.STALE
    assert "data.max_delta_azimuth" in sweep_jobs.stale_error(jobs["full"])
    prepare_job_dir(jobs["full"], root)  # relaunching moves the old result aside first
    assert not (jobs["full"].dir / "metrics.json").exists() and list((root / ".stale").glob("full_s0.*"))
    assert json.loads((jobs["full"].dir / JOB_RECORD).read_text())["config"]["data"]["max_delta_azimuth"] == 123


def test_a_new_component_or_a_removed_key_makes_the_job_stale(tmp_path, monkeypatch):
    study, root = _finished(tmp_path)
    _conf_changes(monkeypatch, lambda cfg: setattr(cfg.loss, "extra", {"_target_": "nvs.losses.terms.X", "weight": 1.0})
                  if "loss" in cfg else None)
    assert {j.row.name: j.status for j in plan(study, root)} == {"full": Status.STALE, "copy": Status.DONE}
    monkeypatch.undo()
    _conf_changes(monkeypatch, lambda cfg: cfg.data.pop("max_delta_azimuth"))
    assert all(j.status == Status.STALE for j in plan(study, root))


def test_changed_row_overrides_change_the_key(tmp_path):
    study, root = _finished(tmp_path)
    changed = {**STUDY, "rows": [{**STUDY["rows"][0], "overrides": ["model/skips=none"]}, STUDY["rows"][1]]}
    jobs = {j.row.name: j for j in plan(load_study(_write(tmp_path, changed)), root)}
    assert jobs["full"].status == Status.STALE and jobs["copy"].status == Status.DONE
    assert "model.skips" in sweep_jobs.stale_error(jobs["full"])


def test_records_from_before_override_keys_are_judged_by_their_config(tmp_path, monkeypatch):
    """A sweep_job.json of the earlier form (key = digest of the whole config, no version) stays a finished job."""
    study, root = _finished(tmp_path)
    for job in plan(study, root):
        record = json.loads((job.dir / JOB_RECORD).read_text())
        legacy = {k: record[k] for k in ("study", "row", "seed", "kind", "overrides", "config")}
        (job.dir / JOB_RECORD).write_text(json.dumps({"key": config_digest(record["config"]), **legacy}))
    assert all(j.status == Status.DONE for j in plan(study, root))
    _conf_changes(monkeypatch, lambda cfg: setattr(cfg.model, "new_switch", False))
    assert all(j.status == Status.DONE for j in plan(study, root))
    monkeypatch.undo()
    _conf_changes(monkeypatch, lambda cfg: setattr(cfg.data, "max_delta_azimuth", 7))  # a default changed
    assert all(j.status == Status.STALE for j in plan(study, root))


def test_config_changes_by_hand():
    old = {"a": 1, "m": {"x": 1, "y": [1, 2]}, "gone": 0}
    new = {"a": 1, "m": {"x": 2, "y": [1, 2], "new": True}, "loss": {"t": {"_target_": "L"}}, "plain": {"k": 1}}
    assert config_changes(old, new) == ["gone", "loss", "m.x"]  # a new node holding a component counts
    assert config_changes(old, old) == []
    assert config_changes(None, new) == ["<config>"]


# -- import rules ----------------------------------------------------------------------------------------------------
def _loaded_after(statement: str, names: tuple[str, ...]) -> list[str]:
    code = f"import sys; {statement}; print([n for n in {names!r} if n in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    return eval(out.stdout.strip().splitlines()[-1])


def test_the_recorder_a_training_job_loads_imports_nothing_heavy():
    heavy = ("lightning", "pandas", "nvs.run.build", "nvs.sweep.jobs", "nvs.sweep.study", "nvs.figures")
    assert _loaded_after("import nvs.sweep.recorder", heavy) == []
    # the target that older commands and docs name still resolves, to the same class
    assert _loaded_after("import nvs.sweep as s, nvs.sweep.recorder as r; assert s.JobRecorder is r.JobRecorder",
                         ("lightning",)) == []


def _loaded_after_each(statements: tuple[str, ...], names: tuple[str, ...]) -> list[list[str]]:
    """What each statement loads of ``names``, in one interpreter: the ``nvs`` modules are dropped from
    ``sys.modules`` before each, so every statement imports the project afresh (torch and Lightning, which no name
    here is, load once: they cost a command line ~5 s of CPU each time)."""
    code = ("import sys\n"
            f"for statement in {statements!r}:\n"
            "    for m in [m for m in sys.modules if m == 'nvs' or m.startswith('nvs.')]: del sys.modules[m]\n"
            "    exec(statement)\n"
            f"    print([n for n in {names!r} if n in sys.modules])\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    return [eval(line) for line in out.stdout.strip().splitlines()[-len(statements):]]


def test_the_sweep_and_the_figures_command_lines_import_no_other_command_line():
    clis = ("nvs.figures", "nvs.sweep.__main__", "nvs.evaluate", "nvs.train", "nvs.bench", "nvs.stress")
    # the last: what the figures library loads when it rebuilds a run
    statements = ("import nvs.sweep.__main__", "import nvs.figures",
                  "import nvs.report.figures, nvs.run.checkpoints, nvs.run.build, nvs.run.compose")
    # the last [] also shows the purge at work: without it the two CLIs loaded before would still be listed
    assert _loaded_after_each(statements, clis) == [["nvs.sweep.__main__"], ["nvs.figures"], []]


def test_a_reference_row_takes_the_data_overrides_it_reads_not_the_validation_ones(tmp_path):
    """Validating on more pairs leaves a reference job as it was; a data override it reads changes its key."""
    def keys(overrides):
        study = load_study(_write(tmp_path, {**STUDY, "overrides": overrides}))
        return {j.row.name: j.key for j in plan(study, tmp_path / "runs")}

    base = keys([])
    more_val = keys(["data.loader.val_pairs_per_model=24"])
    assert more_val["copy"] == base["copy"] and more_val["full"] != base["full"]
    assert keys(["data.train_fraction=0.5"])["copy"] != base["copy"]


def test_the_plan_composes_each_seed_as_hydra_does(tmp_path):
    """The plan composes a row once and sets the seed on a copy; that is the config composing with seed=<n> gives."""
    study = load_study(_write(tmp_path, {**STUDY, "seeds": [0, 3]}))
    for job in plan(study, tmp_path / "runs"):
        direct = sweep_jobs.compose_job(job.kind, [*job.overrides, f"seed={job.seed}"])
        assert job.fingerprint == sweep_jobs.config_fingerprint(direct), (job.row.name, job.seed)
    assert {j.seed for j in plan(study, tmp_path / "runs")} == {0, 3}


def test_a_study_is_never_continued_on_another_render_of_its_data(tmp_path, objects_root):
    """Finished jobs measured on one test set, this machine's data giving another: one error before any launch,
    naming the job, both test sets and the data root. The same test set launches, and the header names it."""
    from nvs.run.build import build_data
    from nvs.sweep.testset import check_launch, job_test_set, local_test_set, signature

    cfg = sweep_jobs.compose_job("train", ["experiment=nvs_chairs", f"data.root={objects_root}", "data.size=64"])
    fingerprint = sweep_jobs.config_fingerprint(cfg)
    here = local_test_set(fingerprint)
    pairs = build_data(cfg).test_pairs()
    assert here == signature(pairs) and here.pairs == len(pairs) > 0

    def finished(name, rows):
        d = tmp_path / name
        d.mkdir()
        (d / "test_per_image.csv").write_text("id_src,id_tgt,l1\n" + "".join(f"{a},{b},0.1\n" for a, b in rows))
        return sweep_jobs.Job(study="s", row=None, seed=0, dir=d, overrides=[], data="chairs")

    new = sweep_jobs.Job(study="s", row=None, seed=1, dir=tmp_path / "new", overrides=[], data="chairs",
                         fingerprint=fingerprint)
    same = finished("same_s0", list(reversed(pairs)))  # order does not matter
    assert job_test_set(same.dir) == here
    check_launch([same], [new])
    other = finished("other_s0", pairs[:-1])
    with pytest.raises(UserError) as err:
        check_launch([same, other], [new])
    msg = str(err.value)
    assert msg.startswith(f"{other.dir}: measured on {len(pairs) - 1} test pairs") and str(objects_root) in msg
    assert f"gives {here}" in msg and "\n" not in msg
    check_launch([other], [])  # nothing to launch: nothing to check
