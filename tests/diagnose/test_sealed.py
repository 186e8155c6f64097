"""The sealed suites stay sealed: their files are the ones docs/diagnose-suite.md records,
their cases are not the tuning cases, and the doc's writers keep each other's sections."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from evaluation import sealed_draw, sealing
from evaluation.scenarios import SEALED_FILE, Scenario, sealed, suite
from evaluation.suitedoc import replace_section, section
from gateway.errors import GatewayError
from gateway.model import effects as fx
from tests import foreign_sealed
from tests.foreign_cases import CASES, sealed_cases

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "diagnose-suite.md"
SEALED = (SEALED_FILE, foreign_sealed.SEALED_FILE)


@pytest.mark.parametrize("path", SEALED, ids=lambda p: p.name)
def test_a_sealed_file_is_the_one_the_doc_records(path):
    """Redrawing or editing a sealed file without recording it (``--reseal REASON``, which
    adds a dated line with the reason to the doc's "## Seals") fails here."""
    digest = sealing.check(DOC, path)
    assert digest == sealing.sha256(path)


@pytest.mark.parametrize("path", SEALED, ids=lambda p: p.name)
def test_the_sealed_sections_name_the_recorded_hash(path):
    """The published sealed table was scored on the recorded file (its hash prefix)."""
    heading = {
        SEALED_FILE: "## Sealed scenarios (never tuned on)",
        foreign_sealed.SEALED_FILE: "## Sealed foreign recordings (never tuned on)",
    }[path]
    text = section(DOC, heading)
    assert text, f"{heading}: not in {DOC.name} (run make suite-table)"
    assert sealing.sha256(path)[:16] in text


def test_an_edited_sealed_file_is_refused(tmp_path):
    doc = tmp_path / "suite.md"
    shutil.copy(DOC, doc)
    copy = tmp_path / "sealed.yaml"
    shutil.copy(SEALED_FILE, copy)
    copy.write_text(copy.read_text().replace("seed: 19", "seed: 29", 1))
    rel = sealing.relative(SEALED_FILE)
    doc.write_text(doc.read_text().replace(f"`{rel}`", f"`{sealing.relative(copy)}`"))
    with pytest.raises(GatewayError, match="reseal"):
        sealing.check(doc, copy)


def test_resealing_is_a_dated_line_with_its_reason(tmp_path):
    doc = tmp_path / "suite.md"
    shutil.copy(DOC, doc)
    copy = ROOT / "sim_plc" / "_sealed_copy_for_test.yaml"
    try:
        copy.write_text(SEALED_FILE.read_text() + "# edited\n")
        with pytest.raises(GatewayError):
            sealing.check(doc, copy)
        sealing.add(doc, copy, "a test reseal")
        assert sealing.check(doc, copy) == sealing.sha256(copy)
        line = [x for x in section(doc, sealing.HEADING).splitlines() if copy.name in x]
        assert len(line) == 1 and "a test reseal" in line[0]
        assert sealing.check(doc, SEALED_FILE)  # the other seals are kept
    finally:
        copy.unlink(missing_ok=True)


def _setting(sc: Scenario) -> tuple:
    return (sc.motion, sc.rate_hz, sc.noise_n, sc.cables, sc.rig, sc.uneven, sc.plant)


def test_the_sealed_scenarios_are_not_tuning_scenarios():
    tuning, held = suite(), sealed()
    assert len(held) >= 20
    assert not {sc.seed for sc in held} & {s for sc in tuning for s in (sc.seed, sc.seed + 500)}
    assert not {sc.name for sc in held} & {sc.name for sc in tuning}
    settings = {_setting(sc) for sc in tuning}
    other = [sc for sc in held if not sc.plant and _setting(sc) not in settings]
    assert len(other) == sum(not sc.plant for sc in held)  # every generated one differs
    assert sum(sc.motion == "moves" for sc in held) >= len(held) // 3  # the other motion
    assert len({sc.rate_hz for sc in held}) >= 3 and len({sc.noise_n for sc in held}) >= 10
    assert sum(not sc.effects for sc in held) >= 5


def test_the_sealed_foreign_cases_are_not_tuning_cases():
    tuning, held = CASES, sealed_cases()
    assert len(held) >= 15
    assert not {c.fo.seed for c in held} & {c.fo.seed for c in tuning}
    assert not {c.fo.pulleys for c in held} & {c.fo.pulleys for c in tuning}
    assert sum(not c.truth for c in held) >= 4
    for case in held:  # every truth parameter has a tolerance
        for params in case.truth.values():
            for value, rel, absol in params.values():
                assert max(rel * abs(value), absol) > 0


def test_replacing_a_section_keeps_the_others(tmp_path):
    doc = tmp_path / "d.md"
    replace_section(doc, "# Top\n\ntuning v1\n")
    replace_section(doc, "## Sealed\n\nsealed v1\n")
    replace_section(doc, "## Real\n\nreal v1\n")
    replace_section(doc, "## Sealed\n\nsealed v2\n")
    replace_section(doc, "# Top\n\ntuning v2\n")
    text = doc.read_text()
    assert text == "# Top\n\ntuning v2\n\n## Sealed\n\nsealed v2\n\n## Real\n\nreal v1\n"


def test_every_effect_is_hidden_in_the_tuning_and_in_both_sealed_suites():
    """Issue #19's done-when: every effect of the catalogue on recordings that hide it, in
    suites one cannot tune to (the foreign generator has no platform: no statics effect)."""
    every = set(fx.EFFECT_NAMES)
    assert every <= {e for sc in suite() for e in sc.effects}
    assert every <= {e for sc in sealed() for e in sc.effects}
    foreign = {e for case in sealed_cases() for e in case.truth}
    assert every - set(fx.stage_of("statics")) <= foreign


def test_the_sealed_foreign_file_is_its_draw_code_output():
    """Every case of ``tests/foreign_sealed.yaml`` is what the draw code gives: the first
    draw untouched, then each appended case drawn alone from its own seed."""
    assert foreign_sealed.load() == foreign_sealed.expected()


def test_the_appended_sealed_twins_are_their_draw_code_output():
    """The twins appended after the sealed scenarios' draw are ``sealed_draw.twin`` of their
    seed, at the end of the file, each once."""
    with open(SEALED_FILE, encoding="utf-8") as fh:
        cases = yaml.safe_load(fh)["scenarios"]
    tail = cases[len(cases) - len(sealed_draw.APPENDED) :]
    assert tail == [sealed_draw.twin(name, seed) for name, seed in sealed_draw.APPENDED]
    assert len({c["name"] for c in cases}) == len(cases)


def test_appending_draws_one_case_and_refuses_a_second(tmp_path):
    """Appending to the first draw keeps every byte of it, gives the draw code's case (the
    checked-in file's last), and refuses a case the file already has."""
    copy = tmp_path / "foreign.yaml"
    foreign_sealed.write(copy, foreign_sealed.FIRST_SEED)
    before = copy.read_bytes()
    (combo, seed), *_ = foreign_sealed.APPENDED
    case = foreign_sealed.append(copy, combo[0], seed)
    assert copy.read_bytes().startswith(before)
    assert foreign_sealed.load(copy)[-1] == case == foreign_sealed.draw_case(combo, seed)
    assert foreign_sealed.load(copy) == foreign_sealed.load()[: len(foreign_sealed.load(copy))]
    after = copy.read_bytes()
    with pytest.raises(ValueError, match="already"):
        foreign_sealed.append(copy, combo[0], seed + 1)
    assert copy.read_bytes() == after
    scen = tmp_path / "scen.yaml"
    shutil.copy(SEALED_FILE, scen)
    with pytest.raises(ValueError, match="already"):
        sealed_draw.append(scen, sealed_draw.APPENDED[0][0], 1)
    assert scen.read_bytes() == SEALED_FILE.read_bytes()
