"""Every bad input gets a clear answer: a typed error, exit 2 and one line on stderr.

The line names the file, and the channel, key or time where they apply (cli.md, STYLE.md
section 5, telemetry.md "Bad input", mill-config.md).  The commands run in-process
through :func:`ident.cli.main`; none of them gets as far as a fit or a training.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ident.cli import main
from ident.errors import MillFileError, RecordingError
from ident.io import parse_mill, read_recording, write_recording
from synth_telemetry import make_synth

RECORDING_COMMANDS = ("segment", "fit", "diagnose", "discrepancy")


@pytest.fixture(scope="module")
def synth(mill):
    return make_synth(mill, seed=2, duration_s=8.0, idle_s=1.0, with_accel=False)


@pytest.fixture(scope="module")
def torque(synth):
    return synth.devices[0]


@pytest.fixture(scope="module")
def good_csv(torque, tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("good") / "rec.csv"
    write_recording(p, [torque])
    return p


def cli(capsys, *argv: str) -> tuple[int, list[str]]:
    """Run ``ident ARGV`` in-process; the exit code and the lines on stderr."""
    capsys.readouterr()
    code = main(list(argv))
    return code, capsys.readouterr().err.strip().splitlines()


def one_line(capsys, *argv: str) -> str:
    """Run a command that must fail on bad input: exit 2 and exactly one stderr line."""
    code, err = cli(capsys, *argv)
    assert code == 2, err
    assert len(err) == 1, err
    return err[0]


def edit_rows(src: Path, dst: Path, fn) -> Path:
    """Copy a CSV, applying ``fn(lines)`` to its list of lines (header at 0)."""
    lines = src.read_text().splitlines()
    fn(lines)
    dst.write_text("\n".join(lines) + "\n")
    return dst


# ---- (a) a recording that is no readable file -----------------------------------------------

def _unreadable(tmp_path: Path) -> Path:
    """A .mcap path that exists but cannot be read (also when the tests run as root)."""
    p = tmp_path / "locked.mcap"
    if os.geteuid() != 0:
        p.write_bytes(b"\x89MCAP0\r\n")
        p.chmod(0)
        return p
    if not Path("/proc/self/mem").exists():
        pytest.skip("no way to make an unreadable file as root here")
    p.symlink_to("/proc/self/mem")  # opens, but reading offset 0 fails with EIO
    return p


def _file(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


BAD_PATHS = {
    "missing": (lambda d: d / "nope.mcap", r"nope\.mcap: unreadable: file not found"),
    "directory": (lambda d: d, r"unreadable: is a directory; expected a recording file"),
    "empty": (lambda d: _file(d / "empty.csv", b""),
              r"empty\.csv: unreadable: the file is empty \(0 bytes\)"),
    "extension": (lambda d: _file(d / "rec.txt", b"time,T_C12\n0,1\n"),
                  r"rec\.txt: unreadable: unknown recording format '\.txt'; expected '\.mcap' "
                  r"or '\.csv'"),
    "unreadable": (_unreadable, r"locked\.mcap: unreadable: cannot read the file"),
}


@pytest.mark.parametrize("what", list(BAD_PATHS))
def test_reader_refuses_a_path_that_is_no_recording(tmp_path, mill, what):
    make, match = BAD_PATHS[what]
    path = make(tmp_path)
    with pytest.raises(RecordingError, match=match) as err:
        read_recording(path, mill)
    assert err.value.path == str(path)


@pytest.mark.parametrize("command", RECORDING_COMMANDS)
@pytest.mark.parametrize("what", list(BAD_PATHS))
def test_commands_exit_2_naming_the_file(tmp_path, mill_path, capsys, command, what):
    make, match = BAD_PATHS[what]
    path = make(tmp_path)
    line = one_line(capsys, command, str(path), "--mill", str(mill_path), "--quiet")
    assert line.startswith(f"ident {command}: error: {path}")
    assert re.search(match, line), line


def test_segment_walks_a_long_recording_only_after_the_path_is_checked(tmp_path, mill, capsys):
    """``recording_span`` (the window walk's first look) used to open the file unguarded."""
    from ident.io import recording_span

    with pytest.raises(RecordingError, match=r"is a directory"):
        recording_span(tmp_path)
    with pytest.raises(RecordingError, match=r"nope\.csv: unreadable: file not found"):
        recording_span(tmp_path / "nope.csv")


# ---- (b) time that steps back or repeats ----------------------------------------------------

def test_csv_time_stepping_back_is_an_error_not_a_dropout(tmp_path, good_csv, mill_path, capsys):
    """Eight rows 40 ms back in time used to be sorted in and reported as a dropout."""
    def back(lines):
        for i in range(2001, 2009):
            cells = lines[i].split(",")
            cells[0] = repr(round(float(cells[0]) - 0.04, 6))
            lines[i] = ",".join(cells)

    p = edit_rows(good_csv, tmp_path / "back.csv", back)
    line = one_line(capsys, "segment", str(p), "--mill", str(mill_path))
    assert line == (f"ident segment: error: {p}, t=0.960000 s: non monotonic: time steps back "
                    "from t=0.999500 s to t=0.960000 s; expected strictly increasing times: "
                    "the order of samples is not guessed")


@pytest.mark.parametrize("encoding", ["json", "protobuf"])
def test_mcap_blocks_that_overlap_are_an_error(tmp_path, torque, mill, encoding):
    from ident.io.writers import McapRecordingWriter

    p = tmp_path / f"overlap-{encoding}.mcap"
    with McapRecordingWriter(p, encoding=encoding) as w:
        cid = w.add_device(torque.name, rate_hz=torque.rate_hz, channels=torque.channels,
                           units=torque.units)
        for k in range(10):
            t0 = torque.t0_ns + (k * 200 - (80 if k == 6 else 0)) * 500_000  # 40 ms back
            w.write_block(cid, t0, torque.data[:, k * 200:(k + 1) * 200])
    with pytest.raises(RecordingError, match=rf"overlap-{encoding}\.mcap, channel "
                       r"'T_C12,T_C34,T_C46,T_C57', t=0\.560000 s: non monotonic: device "
                       r"'/telemetry/torque': a sample block starts at t=0\.560000 s, not after "
                       r"the last sample \(t=0\.599500 s\) of the block before it") as err:
        read_recording(p, mill)
    assert err.value.time == pytest.approx(0.56)


def test_campaign_stores_a_recording_with_time_going_back_as_failed(tmp_path, good_csv, mill,
                                                                     mill_path, capsys):
    """The real reader in the campaign (not the test double): failed, with its reason."""
    from ident.store import Settings, load_results, run_campaign

    folder = tmp_path / "campaign"
    folder.mkdir()
    edit_rows(good_csv, folder / "back.csv", lambda lines: lines.__setitem__(
        1001, lines[1001].replace(lines[1001].split(",")[0], "0.1", 1)))
    url = f"sqlite:///{tmp_path}/r.db"
    s = run_campaign(folder, mill, url, workers=0, progress=False,
                     settings=Settings(fit=False, diagnose=False))
    assert (s.n_found, s.n_done, s.n_failed) == (1, 0, 1)
    name, reason = s.failed[0]
    assert name == "back.csv"
    assert reason.startswith(f"read: {folder / 'back.csv'}, t=0.100000 s: non monotonic: time "
                             "steps back from t=0.499500 s to t=0.100000 s")
    rec = load_results(url)["recordings"].set_index("file_name").loc["back.csv"]
    assert (rec["status"], rec["stage"], rec["error_kind"]) == ("failed", "read",
                                                                 "RecordingError")
    assert rec["error"] == reason
    # the command line: the campaign finishes, exit 3 (some recordings failed)
    code, err = cli(capsys, "campaign", str(folder), "--mill", str(mill_path), "--store",
                    f"sqlite:///{tmp_path}/cli.db", "--workers", "0", "--no-fit",
                    "--no-diagnose")
    assert code == 3
    assert any("failed: back.csv: read:" in e and "non monotonic" in e for e in err)


# ---- (e) a text value in a numeric column ----------------------------------------------------

def test_text_in_a_numeric_column_names_channel_time_and_value(tmp_path, good_csv, mill_path,
                                                               capsys):
    def text(lines):
        cells = lines[50].split(",")
        cells[3] = "abc"  # T_C46 at t = 0.0245 s
        lines[50] = ",".join(cells)

    p = edit_rows(good_csv, tmp_path / "text.csv", text)
    line = one_line(capsys, "segment", str(p), "--mill", str(mill_path), "--quiet")
    assert line == (f"ident segment: error: {p}, channel 'T_C46', t=0.024500 s: unreadable: "
                    "line 51: the value 'abc' is not a number; expected a number, or an empty "
                    "cell, nan or null for a missing sample")
    assert line.count(p.name) == 1  # the file is named once


def test_text_deep_in_a_long_csv_is_found(tmp_path, good_csv, mill):
    """pyarrow's row count restarts per block; the line found is the file's own."""
    def text(lines):
        cells = lines[15001].split(",")
        cells[1] = "n/a?"
        lines[15001] = ",".join(cells)

    p = edit_rows(good_csv, tmp_path / "deep.csv", text)
    with pytest.raises(RecordingError, match=r"deep\.csv, channel 'T_C12', t=7\.500000 s: "
                       r"unreadable: line 15002: the value 'n/a\?' is not a number") as err:
        read_recording(p, mill, chunk_samples=1024)
    assert (err.value.channel, err.value.time) == ("T_C12", pytest.approx(7.5))


def test_bad_time_cell_names_the_time_before(tmp_path, good_csv, mill):
    p = edit_rows(good_csv, tmp_path / "tcell.csv", lambda lines: lines.__setitem__(
        101, "soon" + lines[101][lines[101].index(","):]))
    with pytest.raises(RecordingError, match=r"tcell\.csv, t=0\.049500 s: unreadable: line 102: "
                       r"the time 'soon' is neither float seconds nor an ISO-8601 timestamp "
                       r"\(after t=0\.049500 s\)"):
        read_recording(p, mill)


def test_csv_sibling_errors_name_the_sibling(tmp_path, synth, mill):
    dev = synth.devices[0]
    acc = dataclasses.replace(dev, name="/telemetry/accel", channels=("A_B23_v",),
                              units=("g",), data=dev.data[:1] / 1e3)
    p = tmp_path / "two.csv"
    write_recording(p, [dev, acc])
    sib = tmp_path / "two.accel.csv"
    edit_rows(sib, sib, lambda lines: lines.__setitem__(10, lines[10].split(",")[0] + ",x"))
    with pytest.raises(RecordingError, match=r"two\.accel\.csv, channel 'A_B23_v', "
                       r"t=0\.004500 s: unreadable: line 11: the value 'x' is not a number") as err:
        read_recording(p, mill)
    assert err.value.path == str(sib)
