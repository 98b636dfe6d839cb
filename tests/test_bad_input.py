"""Every bad input gets a clear answer: a typed error, exit 2 and one line on stderr.

The line names the file, and the channel, key or time where they apply (cli.md, STYLE.md
section 5, telemetry.md "Bad input", mill-config.md).  The commands run in-process
through :func:`ident.cli.main`; none of them gets as far as a fit or a training.
"""

from __future__ import annotations

import dataclasses
import os
import re
import stat
from pathlib import Path

import pytest

from ident.cli import main
from ident.errors import MillFileError, RecordingError
from ident.io import iter_recording, parse_mill, read_recording, write_recording
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


# ---- (c) a mapped channel missing from the recording ----------------------------------------

@pytest.fixture(scope="module")
def no_c57(torque, tmp_path_factory) -> Path:
    """The torque device without T_C57 (the upper spindle's gauge)."""
    dev = dataclasses.replace(torque, channels=torque.channels[:3], units=torque.units[:3],
                              data=torque.data[:3])
    p = tmp_path_factory.mktemp("missing") / "no_c57.mcap"
    write_recording(p, [dev])
    return p


def test_segment_warns_about_a_missing_channel_and_goes_on(no_c57, mill_path, capsys):
    code, err = cli(capsys, "segment", str(no_c57), "--mill", str(mill_path))
    assert code == 0
    warned = [e for e in err if "warning" in e]
    assert warned == [f"ident segment: warning: {no_c57}, channel 'T_C57': missing_channel: the "
                      "mill file maps torque channel 'T_C57' but the recording lacks it (it has "
                      "['T_C12', 'T_C34', 'T_C46']); the rest is used"]


@pytest.mark.parametrize("command, need", [
    ("fit", "'ident fit' needs it to compare the model's torque at element C57 with the "
            "measured one"),
    ("discrepancy", "'ident discrepancy' needs it to compare model and measured torque at "
                    "element C57"),
    ("diagnose", "'ident diagnose' needs it for the natural-frequency amplitudes and phases at "
                 "element C57"),
])
def test_commands_that_need_the_channel_exit_2_saying_what_for(no_c57, mill_path, capsys,
                                                               command, need):
    line = one_line(capsys, command, str(no_c57), "--mill", str(mill_path), "--quiet")
    assert line.startswith(f"ident {command}: error: {no_c57}, channel 'T_C57': missing "
                           "channel: the mill file maps torque channel 'T_C57' (element C57) "
                           "but the recording lacks it")
    assert line.endswith(need)


def test_require_channels(no_c57, good_csv, mill):
    from ident.cli.common import require_channels

    rec = read_recording(good_csv, mill, warn=False)  # every torque channel, no accelerometer
    require_channels(rec, mill, "fit")
    require_channels(rec, mill, "diagnose", bearings=())  # a model without bearings
    with pytest.raises(RecordingError, match=r"channel 'A_B23_v': missing channel: the mill file "
                       r"maps acceleration channel 'A_B23_v' \(bearing B23\) but the recording "
                       r"lacks it \(nor 'A_B23_h'\); 'ident diagnose' needs it for the wear state "
                       r"of bearing B23") as err:
        require_channels(rec, mill, "diagnose", bearings=("B23",))
    assert (err.value.path, err.value.channel) == (str(good_csv), "A_B23_v")
    with pytest.raises(RecordingError, match=r"channel 'T_C57'"):
        require_channels(read_recording(no_c57, mill, warn=False), mill, "discrepancy")


def test_a_campaign_records_the_missing_channel_as_a_failed_fit(no_c57, mill):
    """In a campaign the recording fails at its fit, naming file and channel; the segments stay."""
    from ident.store.process import Settings, process_recording

    out = process_recording(no_c57, mill, Settings(diagnose=False))
    assert (out.status, out.stage) == ("failed", "fit")
    assert out.error.startswith(f"fit: {no_c57}, channel 'T_C57': missing channel: the mill "
                                "file maps torque channel 'T_C57' (element C57)")
    assert len(out.segments) >= 2 and out.fit is None


# ---- (d) an unknown key or table in the mill file -------------------------------------------

@pytest.mark.parametrize("old, new, match", [
    ("radius = 0.35", "raduis = 0.35",
     r":71, key 'element\[C12\]\.raduis': unknown key 'raduis'; did you mean 'radius'\?$"),
    ("[operation]", "[operatoin]",
     r":23, key 'operatoin': unknown table \[operatoin\]; did you mean \[operation\]\?$"),
])
def test_misspelt_mill_file_key_exits_2_with_file_line_key_and_suggestion(
        tmp_path, mill_path, capsys, old, new, match):
    bad = tmp_path / "bad.toml"
    text = mill_path.read_text()
    assert text.count(old) == 1
    bad.write_text(text.replace(old, new))
    with pytest.raises(MillFileError, match=match):
        parse_mill(bad.read_text(), path=str(bad))
    line = one_line(capsys, "frequencies", "--mill", str(bad))
    assert line.startswith(f"ident frequencies: error: {bad}:") and re.search(match, line)


# ---- (f) a bad --set ---------------------------------------------------------------------

@pytest.mark.parametrize("item, expected", [
    ("C46.gap=abc", "--set C46.gap=abc: element[C46].gap: must be a number. Got 'abc' instead"),
    ("C46.gap_open=0.01", "--set C46.gap_open=0.01: element[C46].gap_open: gap_open (0.01) must "
                          "not exceed gap (0.002)"),
    ("C64.gap=0.004", "--set C64.gap=0.004: unknown id 'C64' in override 'C64.gap'; did you "
                      "mean 'C46'?"),
    ("C46.gap", "--set C46.gap: expected ID.KEY=VALUE, e.g. C46.gap=0.006"),
])
def test_bad_set_names_the_option_not_the_mill_file(tmp_path, mill_path, capsys, item,
                                                    expected):
    for command in (["simulate", "--out", str(tmp_path / "x.mcap")],
                    ["discrepancy", str(tmp_path / "x.mcap")]):
        line = one_line(capsys, *command, "--mill", str(mill_path), "--set", item, "--quiet")
        assert line == f"ident {command[0]}: error: {expected}"
        assert str(mill_path) not in line
    assert not (tmp_path / "x.mcap").exists()


def test_set_error_keeps_the_key(mill_path):
    import argparse

    from ident.cli.common import load_mill_arg

    with pytest.raises(MillFileError, match=r"^--set C46\.gap=abc: ") as err:
        load_mill_arg(argparse.Namespace(mill=str(mill_path), set=["C46.gap=abc"]))
    assert err.value.key == "element[C46].gap" and err.value.path is None


# ---- (g) --version, and output files that honour the umask ----------------------------------

def test_version(capsys):
    from ident import __version__

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out == f"ident {__version__}\n"


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield 0o640
    os.umask(old)


def test_output_files_honour_the_umask(tmp_path, torque, mill_path, umask_027, capsys):
    out = tmp_path / "f.json"
    assert main(["frequencies", "--mill", str(mill_path), "--out", str(out)]) == 0
    files = [out]
    for name in ("r.mcap", "r.csv"):
        write_recording(tmp_path / name, [torque])
        files.append(tmp_path / name)
    for f in files:
        assert stat.S_IMODE(f.stat().st_mode) == umask_027, f
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


# ---- found by tests/test_fuzz_readers.py ------------------------------------------------------

def test_a_time_stamp_far_in_the_future_is_an_error_not_an_hour_of_nan(tmp_path, good_csv, mill):
    """A damaged last row: before, its gap would be a dropout of NaN rows filling memory."""
    def future(lines):
        lines[-1] = "86400" + lines[-1][lines[-1].index(","):]

    p = edit_rows(good_csv, tmp_path / "future.csv", future)
    with pytest.raises(RecordingError, match=r"future\.csv, channel 'T_C12,T_C34,T_C46,T_C57', "
                       r"t=86400\.000000 s: time jump: time jumps from t=7\.999000 s to "
                       r"t=86400\.000000 s: no row for 86392 s, longer than a dropout may last "
                       r"\(3600 s\); a wrong time stamp\?"):
        read_recording(p, mill)
    with pytest.raises(RecordingError, match=r"future\.csv, t=600\.000000 s: time jump: no "
                       r"sample from t=600\.000000 s for more than a dropout may last \(3600 s\), "
                       r"yet the recording's last time stamp is at t=86400\.000000 s"):
        list(iter_recording(p, mill, window_s=600.0, warn=False))


def test_an_mcap_block_far_from_the_others_is_an_error(tmp_path, torque, mill):
    from ident.io.writers import McapRecordingWriter

    p = tmp_path / "far.mcap"
    with McapRecordingWriter(p) as w:
        cid = w.add_device(torque.name, rate_hz=torque.rate_hz, channels=torque.channels,
                           units=torque.units)
        for k in range(5):
            t0 = torque.t0_ns + k * 100_000_000 + (2 * 86_400 * 10**9 if k == 3 else 0)
            w.write_block(cid, t0, torque.data[:, k * 200:(k + 1) * 200])
    with pytest.raises(RecordingError, match=r"far\.mcap, channel 'T_C12,T_C34,T_C46,T_C57', "
                       r"t=172800\.300000 s: time jump: device '/telemetry/torque': the block at "
                       r"t0_ns=\d+ lies 172800 s after the device's other blocks"):
        read_recording(p, mill)


def test_units_changing_between_the_blocks_of_a_device_are_an_error(tmp_path, torque, mill):
    from mcap.writer import Writer

    from ident.io.sampleblock import encode_protobuf, protobuf_schema

    p = tmp_path / "units.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cid = w.register_channel("/t", "protobuf", sid)
        for k, unit in enumerate(("kN*m", "kN*m", "N*m")):
            t0 = torque.t0_ns + k * 100_000_000
            w.add_message(cid, t0, encode_protobuf(t0, 2000.0, torque.channels, (unit,) * 4,
                                                   torque.data[:, k * 200:(k + 1) * 200]), t0)
        w.finish()
    with pytest.raises(RecordingError, match=r"unit mismatch: device '/t' changes within the "
                       r"recording: a block at t0_ns=\d+ has units \['N\*m', 'N\*m', 'N\*m', "
                       r"'N\*m'\], earlier blocks \['kN\*m'"):
        read_recording(p, mill)


def test_iso_csv_with_an_empty_time_cell(tmp_path, torque, mill):
    p = tmp_path / "iso.csv"
    write_recording(p, [torque], time_format="iso")
    edit_rows(p, p, lambda lines: lines.__setitem__(5, lines[5][lines[5].index(","):]))
    rec = read_recording(p, mill, warn=False)
    assert [i.kind for i in rec.issues] == ["non_monotonic", "dropout"]
    assert "1 rows have no valid time; dropped" in rec.issues[0].message


def test_an_infinite_time_is_a_row_without_a_valid_time(tmp_path, good_csv, mill):
    """The reader drops it (a finding); the span (the window walk's first look) agrees."""
    from ident.io import recording_span

    p = edit_rows(good_csv, tmp_path / "inf.csv", lambda lines: lines.__setitem__(
        -1, "inf" + lines[-1][lines[-1].index(","):]))
    assert recording_span(p) == pytest.approx(7.999)
    rec = read_recording(p, mill, warn=False)
    assert "1 rows have no valid time; dropped" in rec.issues[0].message
    q = edit_rows(good_csv, tmp_path / "nan.csv", lambda lines: lines.__setitem__(
        1, "nan" + lines[1][lines[1].index(","):]))
    with pytest.raises(RecordingError, match=r"nan\.csv: non monotonic: the first and last rows' "
                       r"times \(nan s and 7\.9995 s\) give no span"):
        recording_span(q)
