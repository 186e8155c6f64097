"""``cdpr-gateway fleet --per-robot`` (issue 29 item 1): each robot's recordings diagnosed
jointly as one task -- one report per robot, the report ``diagnose REC REC ...`` gives for
those recordings (:func:`gateway.diagnose.fromfiles.diagnose_file` of the list), one row per
robot x finding x cable, the task sized as its recordings joined."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from gateway.cli import main
from gateway.diagnose.cli import report_json
from gateway.diagnose.fromfiles import diagnose_file
from gateway.fleet import sizing
from gateway.fleet.cli import by_robot, expand
from gateway.fleet.task import JOIN, diagnose_task
from gateway.recordings.reader import Recording, write_recording
from tests import reallike as rl

MACHINES = {
    "a": rl.Machine(cables=3, offset_n=-8.0, noise_frac=0.05),
    "b": rl.Machine(cables=3, c_ns_m=150.0, noise_frac=0.05),
}
"""Two small robots (3 cables), each with its own hidden effect."""
SECONDS = 40.0


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two recordings of each robot in a Hive tree (different motions, 10 Hz, 40 s), and
    the nominal model."""
    d = tmp_path_factory.mktemp("per-robot")
    for robot, machine in MACHINES.items():
        for k, day in enumerate(("2026-01-02", "2026-01-01")):  # later day first on disk
            folder = d / "tree" / f"robot={robot}" / f"date={day}"
            folder.mkdir(parents=True)
            run = rl.Run(seed=11 + 37 * k + (robot == "b"), rate_hz=10.0, seconds=SECONDS, gaps=0)
            rl.write(folder / "part-0000.csv", rl.generate(machine, run))
    model = d / "model.yaml"
    model.write_text(rl.model_yaml(), encoding="utf-8")
    return d / "tree", model


def test_recordings_are_grouped_by_robot_in_order_of_start(fleet_dir, tmp_path) -> None:
    tree, _ = fleet_dir
    groups = by_robot(expand([str(tree)]))
    assert [[Path(p).parent.parent.name for p in g] for g in groups] == [
        ["robot=a", "robot=a"],
        ["robot=b", "robot=b"],
    ]
    for g in groups:  # the Hive date is the start: the earlier day first
        assert [Path(p).parent.name for p in g] == ["date=2026-01-01", "date=2026-01-02"]
    # the metadata's robot wins over the folder
    rec = Recording(
        t=np.arange(20) * 0.1,
        velocity=np.zeros((20, 1)),
        tension_sensor=np.ones((20, 1)),
        metadata={"robot": "zz", "started": "2026-01-01T00:00:00+00:00"},
    )
    (tmp_path / "robot=a").mkdir()
    write_recording(tmp_path / "robot=a" / "x.csv", rec)
    got = by_robot([*expand([str(tree)]), str(tmp_path / "robot=a" / "x.csv")])
    assert [len(g) for g in got] == [2, 2, 1] and got[-1][0].endswith("x.csv")
    # a file whose metadata cannot be read goes with its folder's robot (its task fails)
    (tmp_path / "robot=b").mkdir()
    (tmp_path / "robot=b" / "junk.parquet").write_bytes(b"junk")
    got = by_robot([*expand([str(tree)]), str(tmp_path / "robot=b" / "junk.parquet")])
    assert [len(g) for g in got] == [2, 3] and any(p.endswith("junk.parquet") for p in got[1])


def test_a_robot_task_is_sized_as_its_recordings_joined(tmp_path) -> None:
    n, m = 5_000, 3
    rng = np.random.default_rng(0)
    paths = []
    for k in range(3):
        rec = Recording(
            t=np.arange(n) * 1e-3,
            velocity=rng.normal(0, 0.1, (n, m)),
            tension_sensor=rng.uniform(100, 200, (n, m)),
            tension_platform=rng.uniform(100, 200, (n, m)),
        )
        paths.append(tmp_path / f"r{k}.parquet")
        write_recording(paths[-1], rec)
    one = sizing.estimate(paths[0])
    both = sizing.joined(paths)
    assert one is not None and both is not None
    assert both.rows == 3 * one.rows and both.columns == one.columns and both.exact
    need = both.need_bytes
    assert need - sizing.TASK_BASE_BYTES == pytest.approx(
        3 * (one.need_bytes - sizing.TASK_BASE_BYTES)
    )
    assert sizing.refusal(paths, need) is None
    why = sizing.refusal(paths, need - 1)
    assert why is not None and "3 recordings joined" in why and str(paths[0]) in why
    # one of them unreadable: the joined size is unknown, the task says why itself
    (tmp_path / "bad.parquet").write_bytes(b"junk")
    assert sizing.joined([*paths, tmp_path / "bad.parquet"]) is None
    assert sizing.refusal([*paths, tmp_path / "bad.parquet"], 1) is None


def test_a_robot_task_is_the_joined_diagnosis_of_its_recordings(fleet_dir) -> None:
    """The task of one robot gives the bytes of ``diagnose_file`` of its recordings as a
    list, one set of findings with a ``recordings`` entry per recording."""
    tree, model = fleet_dir
    group = by_robot(expand([str(tree)]))[0]
    res = diagnose_task(group, str(model))
    assert res.error is None, res.error
    assert res.robot == "a" and res.recordings == tuple(group)
    assert res.recording == JOIN.join(group) and res.start == "2026-01-01"
    want = diagnose_file([Path(p) for p in group], model).report
    assert res.report_json == report_json(want)
    rep = json.loads(res.report_json)
    assert [r["name"] for r in rep["recordings"]] == [Path(p).name for p in group]
    assert [(f["effect"], f["cables"]) for f in rep["findings"]] == [("offset", [1, 2, 3])]


@pytest.mark.loopback
def test_fleet_per_robot_writes_one_report_and_one_row_set_per_robot(
    fleet_dir, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """End to end on a LocalCluster of one worker: a report per robot equal to
    ``diagnose_file`` of its recordings, the table's rows per robot x finding x cable."""
    tree, model = fleet_dir
    out = tmp_path / "fleet"
    code = main(
        [
            "fleet",
            str(tree),
            "--model",
            str(model),
            "--out",
            str(out),
            "--per-robot",
            "--workers",
            "1",
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "2 robots (4 recordings), 0 failed" in captured.out
    assert captured.err.count("/2] robot ") == 2
    table = pq.read_table(out / "fleet.parquet").to_pylist()
    reports = sorted(p.name for p in (out / "reports").iterdir())
    assert reports == ["000-robot-a.json", "001-robot-b.json"]
    for group, name in zip(by_robot(expand([str(tree)])), reports, strict=True):
        rep = json.loads((out / "reports" / name).read_text())
        want = diagnose_file([Path(p) for p in group], model).report
        assert rep["findings"] == want["findings"] and rep == want
        rows = [r for r in table if r["report"] == name]
        assert {r["recording"] for r in rows} == {JOIN.join(group)}
        expect = [(f["effect"], c) for f in rep["findings"] for c in f["cables"]]
        assert [(r["effect"], r["cable"]) for r in rows] == (expect or [("none", 0)])
    assert len(table) == sum(1 for r in table if r["report"])  # every row belongs to a robot
    text = (out / "fleet.md").read_text()
    assert "2 robots (4 recordings), 2 diagnosed, 0 failed" in text
    assert sorted(p.name for p in (out / "plots").iterdir()) == ["robot-a.png", "robot-b.png"]
