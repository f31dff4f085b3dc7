"""A study file's typed schema: rows, seeds, a scale and the paper's numbers (``sweeps/README.md`` documents it).

The schema is the dataclasses ``StudyFile`` and ``Row``. ``load_study`` builds them from the YAML mapping through
``nvs.sweep.schema``, so a key that no field declares, a value of the wrong type or a missing required key is one
``UserError`` naming the file, the line and the key (``sweeps/x.yaml:14: rows[2]: unknown key 'colour'; expected one
of [...]``). The checks a type cannot express (row names that name directories, no sweep overrides, reference rows,
evaluation rows) follow in ``_check_row`` and ``_check_evaluates``.

Three kinds of row (``Row.kind``): a trained row ("train": ``experiment`` + ``overrides``, run by ``nvs.train``), a
reference row ("reference": ``reference`` + ``data``, run by ``nvs.evaluate`` without a checkpoint) and an
evaluation row ("evaluate": ``evaluates: <a trained row>`` + ``overrides`` for ``nvs.evaluate``, run on each of that
row's trained jobs' tested checkpoint, e.g. ``route=fit``; ``nvs.sweep.eval_rows``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from omegaconf import OmegaConf

from nvs.core.errors import UserError
from nvs.core.metric_spec import METRICS
from nvs.models.reference import REFERENCE_MODELS  # the one list of the models evaluated without training

REFERENCES = REFERENCE_MODELS
from nvs.sweep.schema import Source, build

# Table layouts: 'metrics' (the paper's tables: metrics, params, costs, paper numbers), 'cost' (cost against error,
# the cheapest row within pick.PICK_L1_TOLERANCE of the best non-oracle L1 marked) or 'convergence' (the metrics
# tables after each job's validation curve under the stopping rule, and <stem>.png: nvs.sweep.convergence_report).
TABLES = ("metrics", "cost", "convergence")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class Row:
    """One table row: a trained configuration (experiment + overrides), a reference model (no training) or an
    evaluation of another row's trained jobs (``evaluates``: its checkpoints through ``nvs.evaluate <overrides>``)."""

    name: str
    label: str = ""                # table text; default: name
    run: str = ""                  # run-directory stem (default: name); the same run in two studies is one job
    experiment: str | None = None
    overrides: tuple[str, ...] = ()
    reference: Literal[REFERENCES] | None = None  # one of REFERENCES: evaluated by nvs.evaluate, one seed
    data: str | None = None        # required for reference rows; for trained rows read from the composed config
    paper: dict[str, float] = field(default_factory=dict)
    oracle: bool = False           # uses ground truth at test time: shown, never the best or the pick of a cost table
    # The row's own seeds (an int N means 0..N-1), replacing the study's 'seeds:' for this row: a row that needs
    # fewer seeds than the table's (Table 3's rows whose paper gap is small). --seeds on the command line replaces
    # both. Not for reference rows (one evaluation stands for every seed).
    seeds: int | tuple[int, ...] | None = None
    # A variant of another trained row of the study, with no paper numbers of its own (the norms-fixed network for
    # the paper's full model): its orderings against the paper are also decided with this row in that row's place
    # (nvs.sweep.paper_order), never against that row itself.
    stands_for: str | None = None
    # An evaluation row: the name of a trained row of the same study whose jobs' tested checkpoints are evaluated by
    # nvs.evaluate with this row's overrides (e.g. [route=fit]), one job per seed of that row, on its data. Such a
    # row has no experiment, reference, data, seeds, paper numbers or stands_for of its own.
    evaluates: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "label", self.label or self.name)
        object.__setattr__(self, "run", self.run or self.name)

    @property
    def kind(self) -> str:
        return "evaluate" if self.evaluates else "reference" if self.reference else "train"


@dataclass(frozen=True)
class StudyFile:
    """The keys a study file may hold, with their types; ``size``, ``steps`` and ``rows`` are required."""

    size: int
    steps: int
    rows: tuple[Row, ...]
    name: str | None = None        # default: the file name
    title: str | None = None
    description: str | None = None
    paper_source: str | None = None
    paper_scale: Any = None        # free text about the paper's scale (documentation only)
    seeds: int | tuple[int, ...] = (0,)  # an int N means 0..N-1
    overrides: tuple[str, ...] = ()
    metrics: tuple[str, ...] | None = None  # default: every metric
    group_by: Literal["data"] | None = None
    table: Literal[TABLES] = "metrics"
    # Rows every other trained row of the same table is compared with (the fidelity study: the authors' code); in
    # each table the first of them that the table holds is the base.
    against: tuple[str, ...] = ()


@dataclass(frozen=True)
class Study:
    """A loaded study at the scale and seeds chosen for this run (the file's, or the command line's)."""

    name: str
    path: Path
    title: str
    description: str
    paper_source: str
    seeds: tuple[int, ...]
    size: int
    steps: int
    default_size: int
    default_steps: int
    overrides: tuple[str, ...]
    metrics: tuple[str, ...]
    group_by: str | None
    rows: tuple[Row, ...]
    table: str = "metrics"
    against: tuple[str, ...] = ()
    seeds_from_command_line: bool = False  # --seeds given: every trained row runs these, whatever its own 'seeds:'

    @property
    def scale(self) -> str:
        return f"{self.size}px_{self.steps}steps"

    @property
    def results_stem(self) -> str:
        """``<study>`` at the study's own scale; other scales get their own files instead of overwriting it."""
        default = self.size == self.default_size and self.steps == self.default_steps
        return self.name if default else f"{self.name}_{self.scale}"


# -- the checks a type cannot express --------------------------------------------------------------------------------
def _check_overrides(where: str, overrides: tuple[str, ...]) -> tuple[str, ...]:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except Exception as err:  # noqa: BLE001 - Hydra's parser raises several types; all mean a malformed override
        raise UserError(f"{where}: {err}") from None
    for o in parsed:
        if o.is_sweep_override():
            raise UserError(f"{where}: override '{o.input_line}' is a sweep; make each value its own row")
        # The seed names the job directory and the size names the scale: both belong to the study, not a row.
        if o.key_or_group in ("seed", "data.size"):
            raise UserError(f"{where}: '{o.input_line}' is set by the study ('seeds:' / 'size:', --seeds / --size)")
    return overrides


def _check_row(row: Row, where: str) -> None:
    _check_overrides(where, row.overrides)
    for key in (row.name, row.run):
        if not _NAME.match(key):
            raise UserError(f"{where}: '{key}' must be letters, digits, '_', '.', '-' (it names a directory)")
    if row.reference is not None and (row.experiment or not row.data):
        raise UserError(f"{where}: a reference row names 'data' and no 'experiment'")
    bad = [m for m in row.paper if m not in METRICS]
    if bad:
        raise UserError(f"{where}: paper numbers for unknown metric(s) {bad}")
    if row.seeds is not None:
        if row.reference is not None:
            raise UserError(f"{where}: a reference row has no 'seeds' (one evaluation stands for every seed)")
        own = seed_list(row.seeds)
        if not own or len(set(own)) != len(own) or min(own) < 0:
            raise UserError(f"{where}: seeds must be distinct, non-negative and at least one, got {own}")


# What an evaluation row takes from the row it evaluates, not from its own keys.
_NOT_FOR_EVALUATION = {"experiment": "its checkpoints carry their config", "reference": "it evaluates trained jobs",
                       "data": "its data is the evaluated row's", "seeds": "its seeds are the evaluated row's",
                       "paper": "it has no paper numbers", "stands_for": "it evaluates a row, it stands for none",
                       "oracle": "the evaluated row says whether ground truth is used"}


def _check_evaluates(rows: tuple[Row, ...], source: Source) -> None:
    """An evaluation row ('evaluates:') names a trained row of the study and sets none of the keys that row owns; its
    overrides are nvs.evaluate's, and the checkpoint is the runner's to give."""
    by_name = {row.name: row for row in rows}
    trained = [r.name for r in rows if r.kind == "train"]
    for i, row in enumerate(rows):
        if row.evaluates is None:
            continue
        for key, why in _NOT_FOR_EVALUATION.items():
            value = getattr(row, key)
            if value not in (None, {}, False):
                raise UserError(f"{source.where(('rows', i, key))}: an evaluation row (evaluates: {row.evaluates}) "
                                f"has no '{key}' ({why})")
        for j, o in enumerate(row.overrides):
            if o.lstrip("+~").split("=", 1)[0] == "ckpt_path":
                raise UserError(f"{source.where(('rows', i, 'overrides', j))}: '{o}': the checkpoint is the "
                                f"evaluated job's ('{row.evaluates}'), given by the runner")
        where = source.where(("rows", i, "evaluates"))
        target = by_name.get(row.evaluates)
        if target is None or target.kind != "train":
            what = ("is not a row of the study" if target is None else
                    f"is {'an evaluation' if target.kind == 'evaluate' else 'a reference'} row, not a trained one")
            raise UserError(f"{where}: '{row.evaluates}' {what}; an evaluation row evaluates one of: "
                            f"{', '.join(trained) or 'none'}")


def _check_stands_for(rows: tuple[Row, ...], source: Source) -> None:
    """A variant ('stands_for:') names another trained row with paper numbers, which is no variant itself, and has no
    paper numbers of its own (one row's numbers, one place in the paper's orderings)."""
    by_name = {row.name: row for row in rows}
    for i, row in enumerate(rows):
        if row.stands_for is None:
            continue
        where = source.where(("rows", i, "stands_for"))
        target = by_name.get(row.stands_for)
        if row.stands_for == row.name:
            raise UserError(f"{where}: row '{row.name}' cannot stand for itself")
        if target is None:
            raise UserError(f"{where}: '{row.stands_for}' is not a row of the study")
        if target.stands_for is not None:
            raise UserError(f"{where}: '{target.name}' stands for '{target.stands_for}' itself; name that row "
                            "(no chains)")
        if target.kind != "train" or not target.paper:
            named = [r.name for r in rows if r.kind == "train" and r.paper]
            raise UserError(f"{where}: '{target.name}' is not a trained row with paper numbers; a variant stands "
                            f"for one of: {', '.join(named) or 'none'}")
        if row.paper:
            raise UserError(f"{where}: row '{row.name}' has paper numbers of its own; a variant is read against "
                            f"those of '{target.name}'")


def seed_list(seeds: int | tuple[int, ...]) -> list[int]:
    """A study's or row's 'seeds:' value as a list: an int N means 0..N-1."""
    return list(range(seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]


def row_seeds(study: Study, row: Row) -> tuple[int, ...]:
    """The seeds a row runs: the study's; the row's own 'seeds:' unless --seeds was given; one for a reference row
    (a reference model has nothing to train: one evaluation stands for every seed); an evaluation row's are those
    of the row it evaluates."""
    if row.evaluates:
        return row_seeds(study, next(r for r in study.rows if r.name == row.evaluates))
    if row.reference:
        return study.seeds[:1]
    if row.seeds is not None and not study.seeds_from_command_line:
        return tuple(seed_list(row.seeds))
    return study.seeds


def load_study(path: str | Path, seeds: list[int] | None = None, size: int | None = None,
               steps: int | None = None) -> Study:
    """Read and validate a study file; ``seeds``/``size``/``steps`` replace the file's values."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such study file")
    try:
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as err:  # noqa: BLE001 - YAML and interpolation errors alike mean a malformed file
        raise UserError(f"{path}: not a readable study file: {str(err).splitlines()[0]}") from None
    if not isinstance(raw, dict):
        raise UserError(f"{path}: a study file is a mapping (name, seeds, size, steps, rows, ...)")
    source = Source(path)
    spec: StudyFile = build(StudyFile, raw, source)
    metrics = spec.metrics or METRICS
    bad = [m for m in metrics if m not in METRICS]
    if bad:
        raise UserError(f"{source.where(('metrics',))}: unknown metric(s) {bad}; expected some of {list(METRICS)}")
    _check_evaluates(spec.rows, source)  # first: an evaluation row's own keys are named before any other check
    names, runs = set(), set()
    for i, row in enumerate(spec.rows):
        where = source.where(("rows", i))
        _check_row(row, where)
        if row.name in names or row.run in runs:
            raise UserError(f"{where}: row name '{row.name}' / run '{row.run}' used twice in the study")
        names.add(row.name)
        runs.add(row.run)
    if not spec.rows:
        raise UserError(f"{source.where(('rows',))}: 'rows' is empty")
    trained = [row.name for row in spec.rows if row.kind == "train"]
    _check_stands_for(spec.rows, source)
    for i, base in enumerate(spec.against):
        if base not in trained:
            raise UserError(f"{source.where(('against', i))}: '{base}' is not a trained row of the study; "
                            f"trained rows: {', '.join(trained)}")
    file_seeds = seed_list(spec.seeds)
    chosen = [int(s) for s in (seeds if seeds is not None else file_seeds)]
    if not chosen or len(set(chosen)) != len(chosen):
        raise UserError(f"{source.where(('seeds',))}: seeds must be distinct and at least one, got {chosen}")
    name = spec.name or path.stem
    return Study(
        name=name, path=path, title=spec.title or name, description=spec.description or "",
        paper_source=spec.paper_source or "", seeds=tuple(chosen),
        size=int(size if size is not None else spec.size), steps=int(steps if steps is not None else spec.steps),
        default_size=spec.size, default_steps=spec.steps,
        overrides=_check_overrides(source.where(("overrides",)), spec.overrides),
        metrics=tuple(metrics), group_by=spec.group_by, rows=spec.rows, table=spec.table,
        against=tuple(spec.against), seeds_from_command_line=seeds is not None)
