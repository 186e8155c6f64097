"""The diagnosis of files, one way for every caller: ``diagnose`` (:mod:`.cli`), ``calibrate``
(:mod:`sim_plc.calibrate`) and the fleet's task (:mod:`gateway.fleet.task`).

:func:`diagnose_file`: one or several recordings of one machine and a model file ->
:class:`FileDiagnosis`. Each recording is read relative to the model's fitted effects
(:func:`gateway.diagnose.writemodel.relative_to_model`), optionally cut to the rows a caller
keeps (``rows``) and split into a part to fit and a part to validate on (``split``); the
reference follows from the first recording's columns (:func:`.engine.reference_mode`):

- **platform tensions** (``tension_platform_i`` columns, or tensions from pose and mass:
  :mod:`.pose_statics`): each recording slimmed as soon as it is read (the cable lengths,
  then pose and mass once its platform tensions and dT_p/dm exist), several joined
  (:func:`.sessions.join`), the platform-tension reference;
- **wrench balance** (none of them has platform tensions): several joined
  (:func:`.sessions.join_wrench`), the wrench reference
  (:class:`.wrench_reference.WrenchReference`);

then :func:`.engine.diagnose`, and the start-up transient said as such
(:func:`.transient.annotate`). A single recording is diagnosed as itself, never as a
join of one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from gateway.core.config import Config, FrictionConfig, config_from_mapping, load_friction
from gateway.core.configtypes import read_yaml
from gateway.diagnose import heldout, pose_statics, transient
from gateway.diagnose.engine import diagnose, load_kernels, reference_mode
from gateway.diagnose.report import Diagnosis
from gateway.diagnose.sessions import join, join_wrench
from gateway.diagnose.wrench_reference import WrenchReference
from gateway.diagnose.writemodel import relative_to_model, write_model
from gateway.errors import GatewayError
from gateway.recordings.reader import Recording, read_recording

Say = Callable[[str], None]
Rows = Callable[[Recording], Recording]
Split = Callable[[Recording], tuple[Recording, Recording]]


@dataclasses.dataclass
class FileDiagnosis:
    """One diagnosis of files: the result, the recording diagnosed (several: joined) and
    what the model writer needs (:meth:`write_model`)."""

    diag: Diagnosis
    rec: Recording
    fitted_from: Recording
    """What the model writer reads of the recording (the first cable lengths)."""
    model: Path
    model_friction: FrictionConfig

    @property
    def report(self) -> dict:
        return self.diag.report

    def write_model(
        self, path: Path, label: str | None = None, where: str = "the --validate recording"
    ) -> None:
        """The model plus every fitted effect in ``path``, unless the held-out check
        refuses it (:func:`.heldout.refusal`: a :class:`GatewayError` naming ``label``,
        default the path; ``where``: what the validation is)."""
        refused = heldout.refusal(self.report, heldout.motion(self.rec.t, self.rec.velocity), where)
        if refused is not None:
            raise GatewayError(f"{label or path}: {refused}")
        write_model(path, self.model, self.model_friction, self.report, self.fitted_from)


def load_model(path: Path) -> tuple[FrictionConfig, Config | None]:
    """The friction config and, if the file is a full config with a geometry, the config."""
    data = read_yaml(path)
    friction = load_friction(path)
    cfg = config_from_mapping(data, str(path)) if "geometry" in data else None
    return friction, cfg


def diagnose_file(
    recordings: Path | Sequence[Path],
    model: Path,
    validate: Path | None = None,
    *,
    columns: Mapping[str, str] | None = None,
    rows: Rows | None = None,
    split: Split | None = None,
    progress: Say | None = None,
) -> FileDiagnosis:
    """Diagnose ``recordings`` (one path, or a list of one machine's, diagnosed together for
    one set of findings) against the model file ``model`` (module docstring); bad input
    raises :class:`GatewayError`.

    ``validate``: a second recording of the same machine, scored but never fitted;
    ``columns``: a column map (:func:`gateway.recordings.columns.column_map`) for every
    file read; ``rows``: the rows of a recording to diagnose (applied as it is read, before
    the model's effects are undone); ``split``: each recording -> (the part to fit, the part
    to validate on), the validation parts taking the place of ``validate``.
    """
    say = progress or _silent
    if isinstance(recordings, list | tuple):
        paths = [Path(p) for p in recordings]
    else:
        paths = [Path(recordings)]  # type: ignore[arg-type]
    if split is not None and validate is not None:
        raise GatewayError(f"{validate}: a validation recording and a split of each: one only")
    model = Path(model)
    model_friction, cfg = load_model(model)
    load_kernels(model_friction)  # LLVM's pages given back after
    files = _Files(model_friction, cfg, columns, rows, split, say)
    if reference_mode(files.first(paths[0])) == "wrench":  # no platform tensions
        diag, rec, fitted_from, nominal = _wrench(files, paths, validate, cfg, say)
    else:
        diag, rec, fitted_from, nominal = _platform(files, paths, validate, cfg, say)
    transient.annotate(diag.report, rec, nominal)  # the start-up transient, said as such
    return FileDiagnosis(diag, rec, fitted_from, model, model_friction)


@dataclasses.dataclass
class _Files:
    """How each file is read: relative to the model, its rows, its split."""

    friction: FrictionConfig
    cfg: Config | None
    columns: Mapping[str, str] | None
    rows: Rows | None
    split: Split | None
    say: Say
    nominal: FrictionConfig | None = None
    _first: tuple[Recording, Recording | None] | None = None
    validations: list[Recording] = dataclasses.field(default_factory=list)

    def first(self, path: Path) -> Recording:
        """The first recording, read once (:meth:`read` gives it back, once)."""
        self._first = self._read(path)
        return self._first[0]

    def read(self, path: Path, k: int) -> Recording:
        """Recording ``k`` (its validation part, if split, kept in :attr:`validations`)."""
        if k == 0 and self._first is not None:
            rec, check = self._first
            self._first = None
        else:
            rec, check = self._read(path)
        if check is not None:
            self.validations.append(check)
        return rec

    def _read(self, path: Path) -> tuple[Recording, Recording | None]:
        """A recording relative to the model's fitted effects (``friction.effects``) and the
        nominal friction (:func:`relative_to_model`). Without effects or a row filter, only
        the first row of the cable lengths is read: the diagnosis reads none of them, the
        model writer the first (the eccentricity's phase); undoing effects and a row filter
        need all of them."""
        first_only = () if self.friction.effects or self.rows is not None else ("length",)
        rec = read_recording(path, first_row_only=first_only, columns=self.columns)
        if self.rows is not None:
            rec = self.rows(rec)
            self.say(f"{path}: {rec.samples} rows kept ({rec.skipped_rows} left out)")
        rec, self.nominal = relative_to_model(rec, self.friction, self.cfg)
        if self.split is None:
            return rec, None
        fit, check = self.split(rec)
        self.say(f"{path}: fit on the first {fit.samples} rows, validate on {check.samples}")
        return fit, check

    def validation(self, validate: Path | None) -> list[Recording]:
        """The validation recordings: the split's parts, or ``validate`` read."""
        if validate is not None:
            return [self._read(validate)[0]]
        return self.validations


def _shape(rec: Recording) -> str:
    skipped = f", {rec.skipped_rows} rows skipped (missing values)" if rec.skipped_rows else ""
    return f"{rec.source}: {rec.samples} samples x {rec.cables} cables{skipped}"


def _platform(files: _Files, paths: list[Path], validate: Path | None, cfg: Config | None, say):
    """The platform-tension reference: each recording slimmed as it is read, several
    joined (:mod:`.sessions`)."""
    parts = []
    keep_for_model: Callable[[Recording], Recording] | None = None
    for k, path in enumerate(paths):
        rec = files.read(path, k)
        say(_shape(rec))
        if reference_mode(rec) == "wrench":
            raise GatewayError(
                f"{path}: no tension_platform_i columns, {paths[0]} has them: the "
                "recordings diagnosed together must all have platform tensions or none"
            )
        rec, keep = _slim(rec)
        keep_for_model = keep_for_model or keep  # the model writer reads the first's lengths
        tp, dm = _tensions(rec, cfg, say)
        parts.append((_without_pose(rec), tp, dm))
    if len(parts) == 1:
        (rec, tp, dm), sessions = parts[0], None
    else:
        rec, tp, dm, sessions = join(parts, [str(p) for p in paths])
        say(f"{sessions.count} recordings joined: {rec.samples} samples")
    del parts
    vrecs = files.validation(validate)
    if len(vrecs) > 1:
        raise GatewayError(
            f"{paths[0]}: several validation recordings: the platform-tension reference scores one"
        )
    validation = None
    if vrecs:
        vrec = dataclasses.replace(vrecs[0], length=None)
        vtp, vdm = _tensions(vrec, cfg, say)
        validation = (_without_pose(vrec), vtp, vdm if dm is not None else None)
    del vrecs
    nominal = files.nominal
    assert nominal is not None  # every recording read sets it
    diag = diagnose(
        rec, nominal, tp=tp, dtp_dm=dm, validation=validation, progress=say, sessions=sessions
    )
    assert keep_for_model is not None
    return diag, rec, keep_for_model(rec), nominal


def _wrench(files: _Files, paths: list[Path], validate: Path | None, cfg: Config | None, say):
    """The wrench reference: the recordings (and the validation recordings), several
    joined (:func:`.sessions.join_wrench`)."""
    recs = []
    for k, path in enumerate(paths):
        rec = files.read(path, k)
        if reference_mode(rec) != "wrench":
            raise GatewayError(
                f"{path}: tension_platform_i columns, {paths[0]} has none: the "
                "recordings diagnosed together must all have platform tensions or none"
            )
        recs.append(rec)
    for rec in recs:
        say(_shape(rec))
    sessions = vsessions = None
    if len(recs) == 1:
        rec = recs[0]
    else:
        rec, sessions = join_wrench(recs, [str(p) for p in paths])
        say(f"{sessions.count} recordings joined: {rec.samples} samples (wrench reference)")
    del recs
    vrecs = files.validation(validate)
    vrec = None
    if len(vrecs) == 1:
        vrec = vrecs[0]
    elif vrecs:
        vnames = [v.source or f"validation {k + 1}" for k, v in enumerate(vrecs)]
        vrec, vsessions = join_wrench(vrecs, vnames)
    del vrecs
    nominal = files.nominal
    assert nominal is not None  # every recording read sets it
    reference = WrenchReference(cfg, sessions, vsessions)
    diag = diagnose(rec, nominal, reference, validation=vrec, progress=say)
    return diag, rec, rec, nominal


def _tensions(rec: Recording, cfg: Config | None, say):
    """Platform tensions (N, m) and dT_p/dm (N, m) or None."""
    if rec.tension_platform is not None:
        tp = rec.tension_platform
    else:
        say(f"{rec.source}: platform tensions from pose and mass (statics)")
        tp = pose_statics.platform_tensions(rec, cfg)
    return tp, pose_statics.mass_sensitivity(rec, cfg, say)


def _slim(rec: Recording) -> tuple[Recording, Callable[[Recording], Recording]]:
    """The recording without its cable lengths, which the diagnosis does not read (64
    bytes per sample of 8 cables when they were read whole), and a function that gives the
    model writer back what it reads of them (the first lengths, for the eccentricity's
    phase). Pose and mass go too once the platform tensions and dT_p/dm exist
    (:func:`_without_pose`)."""
    first = None if rec.length is None else rec.length[:1].copy()

    def keep_for_model(r: Recording) -> Recording:
        return dataclasses.replace(r, length=first)  # one row: write_model reads length[0]

    return dataclasses.replace(rec, length=None), keep_for_model


def _without_pose(rec: Recording) -> Recording:
    """``rec`` without pose and mass (56 bytes per sample), read by :func:`_tensions` only."""
    return dataclasses.replace(rec, pose=None, mass=None)


def _silent(msg: str) -> None:
    pass
