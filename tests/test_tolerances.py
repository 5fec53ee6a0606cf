"""The one route of every tolerance: overrides, files, and the CLI's options."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadio.tolerances import DEFAULT_TOLERANCES, read_tolerances, write_tolerances
from flows.cli import main


def test_overrides_replace_only_what_they_name() -> None:
    tol = DEFAULT_TOLERANCES.with_overrides({"contact_mm": "0.25", "coaxial_deg": 1})
    assert tol.contact_mm == 0.25 and tol.coaxial_deg == 1.0
    others = {k: v for k, v in tol.as_dict().items() if k not in ("contact_mm", "coaxial_deg")}
    assert others == {k: v for k, v in DEFAULT_TOLERANCES.as_dict().items() if k in others}


@pytest.mark.parametrize(("overrides", "message"), [
    ({"contact": 0.2}, "unknown tolerance 'contact'; known: coaxial_deg"),
    ({"contact_mm": "a lot"}, "must be a number"),
    ({"contact_mm": -1}, "finite and >= 0"),
    ({"contact_mm": "nan"}, "finite and >= 0"),
    ({"contact_mm": "inf"}, "finite and >= 0"),
])
def test_bad_overrides_say_what_is_wrong(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DEFAULT_TOLERANCES.with_overrides(overrides)  # type: ignore[arg-type]


def test_a_runs_file_reads_back(tmp_path: Path) -> None:
    tol = DEFAULT_TOLERANCES.with_overrides({"grid_margin": 0.1})
    write_tolerances(tmp_path / "tolerances.json", tol)
    assert read_tolerances(tmp_path / "tolerances.json") == tol


def test_cli_rejects_an_unknown_tolerance(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["mates", str(tmp_path / "x.step"), "--tol", "contactmm=0.2"])
    assert code == 2
    assert "unknown tolerance 'contactmm'" in capsys.readouterr().err
    assert main(["mates", str(tmp_path / "x.step"), "--tol", "contact_mm"]) == 2
