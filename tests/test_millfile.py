"""The mill file contract (../shared/spec/mill-config.md): every refusal names key and line.

Each case edits the shipped ``data/mills/hsm-f1.toml`` in one place and checks the
message (``match``), the dotted ``key`` and the 1-based ``line`` of the error.
"""

from __future__ import annotations

import dataclasses

import pytest

from ident import Mill, MillFileError, StiffnessKind, load_mill, parse_mill

PATH = "mills/test.toml"


@pytest.fixture(scope="module")
def text(mill_path) -> str:
    return mill_path.read_text(encoding="utf-8")


def edit(text: str, old: str, new: str) -> str:
    """Replace the one occurrence of ``old`` (asserting it is there exactly once)."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times"
    return text.replace(old, new)


def line_of(text: str, needle: str, *, after: str | None = None) -> int:
    """1-based line of the first line containing ``needle`` (after the line with ``after``)."""
    lines = text.splitlines()
    start = 0
    if after is not None:
        start = next(i for i, ln in enumerate(lines) if after in ln) + 1
    return next(i for i, ln in enumerate(lines) if i >= start and needle in ln) + 1


def refuse(text: str, match: str) -> MillFileError:
    with pytest.raises(MillFileError, match=match) as info:
        parse_mill(text, path=PATH)
    err = info.value
    assert isinstance(err, ValueError)        # generic handlers still catch it
    assert err.path == PATH and str(err).startswith(PATH)
    return err


# --- the shipped file -------------------------------------------------------------------------

def test_shipped_file_loads(mill_path):
    mill = load_mill(mill_path)
    assert isinstance(mill, Mill)
    assert mill.name == "hsm-f1"
    assert mill.mass_ids == ("Q1", "Q2", "Q3", "Q4", "Q5", "Q6", "Q7")
    assert mill.element_ids == ("C12", "C23", "C34", "C45", "C46", "C57")
    c46 = mill.element("C46")
    assert (c46.from_, c46.to, c46.k, c46.gap, c46.gap_open) == ("Q4", "Q6", 1.815e7, 0.002, 0.0)
    assert c46.stiffness is StiffnessKind.LINEAR and c46.k_gap == 0.0
    assert mill.load.masses == ("Q6", "Q7") and mill.load.share == (0.5, 0.5)
    assert [b.id for b in mill.bearings] == ["B23", "B45"]
    assert len(mill.channels) == 8 and len(mill.torque_channels()) == 4
    assert mill.source == str(mill_path) and len(mill.sha256) == 64
    with pytest.raises(dataclasses.FrozenInstanceError):
        mill.name = "x"


def test_missing_file_is_refused(tmp_path):
    with pytest.raises(MillFileError, match="mill file not found") as info:
        load_mill(tmp_path / "nope.toml")
    assert info.value.path == str(tmp_path / "nope.toml")


# --- refusals -------------------------------------------------------------------------------

@pytest.mark.parametrize("old, new, match, key, header", [
    ("k = 3.305e7\n", "", r"required key 'k' is missing", "element[C12].k", 'id = "C12"'),
    ("J = 3249.0\n", "", r"required key 'J' is missing", "mass[Q1].J", 'id = "Q1"'),
    ('masses = ["Q6", "Q7"]\n', "", r"required key 'masses' is missing", "load.masses", "[load]"),
    ('name = "hsm-f1"\n', "", r"required key 'name' is missing", "mill.name", "[mill]"),
])
def test_missing_required_key(text, old, new, match, key, header):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert err.key == key
    # the key is absent, so the line is the table's header
    hdr = line_of(bad, header) - (0 if header.startswith("[") else 1)
    assert err.line == hdr
    assert bad.splitlines()[err.line - 1].lstrip().startswith("[")


def test_missing_required_table(text):
    motor = text[text.index("[motor]\n"):text.index("[[bearing]]")]
    err = refuse(edit(text, motor, ""), r"required table \[motor\] is missing")
    assert err.key == "motor" and err.line is None


def test_misspelt_required_table_is_named(text):
    bad = edit(text, "[motor]\n", "[motor_x]\n")
    err = refuse(bad, r"unknown table \[motor_x\]; did you mean \[motor\]\?")
    assert (err.key, err.line) == ("motor_x", line_of(bad, "[motor_x]"))


@pytest.mark.parametrize("old, new, key, needle", [
    ('from = "Q1"', 'from = "Q9"', "element[C12].from", 'from = "Q9"'),
    ('to = "Q7"', 'to = "Q9"', "element[C57].to", 'to = "Q9"'),
    ('masses = ["Q6", "Q7"]', 'masses = ["Q6", "Q9"]', "load.masses", "masses ="),
    ('[motor]\nmass = "Q1"', '[motor]\nmass = "Q9"', "motor.mass", 'mass = "Q9"'),
])
def test_unknown_mass_id(text, old, new, key, needle):
    bad = edit(text, old, new)
    err = refuse(bad, r"unknown mass id 'Q9'; known masses: \['Q1', .*'Q7'\]")
    assert err.key == key
    assert err.line == line_of(bad, needle)


@pytest.mark.parametrize("old, new, match, key, needle", [
    ('element = "C46"', 'element = "C99"', r"unknown element id 'C99'", "channel[T_C46].element",
     'element = "C99"'),
    ('mesh = "C45"', 'mesh = "C99"', r"unknown element id 'C99'", "bearing[B45].mesh",
     'mesh = "C99"'),
    ('name = "A_B45_v"\nquantity = "acceleration"\nbearing = "B45"',
     'name = "A_B45_v"\nquantity = "acceleration"\nbearing = "B99"',
     r"unknown bearing id 'B99'", "channel[A_B45_v].bearing", 'bearing = "B99"'),
])
def test_unknown_id_in_channel_or_bearing(text, old, new, match, key, needle):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert (err.key, err.line) == (key, line_of(bad, needle))


def test_unknown_mass_in_speed_channel(text):
    bad = text + '\n[[channel]]\nname = "n_Q9"\nquantity = "speed"\nmass = "Q9"\nunit = "rpm"\n'
    err = refuse(bad, r"unknown mass id 'Q9'")
    assert (err.key, err.line) == ("channel[n_Q9].mass", line_of(bad, 'mass = "Q9"'))


@pytest.mark.parametrize("old, new, match, key, needle", [
    ("J = 3249.0", "J = 0.0", r"must be positive. Got 0.0 instead", "mass[Q1].J", "J = 0.0"),
    ("J = 1966.0", "J = -1966.0", r"must be positive. Got -1966.0 instead", "mass[Q2].J",
     "J = -1966.0"),
    ("k = 3.305e7", "k = 0", r"must be positive. Got 0.0 instead", "element[C12].k", "k = 0"),
    ("k = 1.537e7", "k = -1.537e7", r"must be positive. Got -15370000.0 instead",
     "element[C57].k", "k = -1.537e7"),
    ('J = 3249.0', 'J = "heavy"', r"must be a number. Got 'heavy' instead", "mass[Q1].J",
     'J = "heavy"'),
])
def test_non_positive_inertia_or_stiffness(text, old, new, match, key, needle):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert (err.key, err.line) == (key, line_of(bad, needle))


def test_element_joining_a_mass_to_itself(text):
    bad = edit(text, 'from = "Q4"\nto = "Q6"', 'from = "Q6"\nto = "Q6"')
    err = refuse(bad, r"element joins mass 'Q6' to itself")
    assert (err.key, err.line) == ("element[C46].to", line_of(bad, 'to = "Q6"'))


def test_gap_open_larger_than_gap(text):
    bad = edit(text, 'to = "Q6"\nk = 1.815e7\nc = 4.5e3\nratio = 2.5\ngap = 0.002\ngap_open = 0.0',
               'to = "Q6"\nk = 1.815e7\nc = 4.5e3\nratio = 2.5\ngap = 0.002\ngap_open = 0.003')
    err = refuse(bad, r"gap_open \(0.003\) must not exceed gap \(0.002\)")
    assert (err.key, err.line) == ("element[C46].gap_open", line_of(bad, "gap_open = 0.003"))


@pytest.mark.parametrize("share", ["[0.5, 0.6]", "[1.2, -0.2]"])
def test_load_shares_not_summing_to_one(text, share):
    bad = edit(text, "share = [0.5, 0.5]", f"share = {share}")
    err = refuse(bad, r"shares must be non-negative and sum to 1")
    assert (err.key, err.line) == ("load.share", line_of(bad, "share = "))


def test_load_share_count_must_match_masses(text):
    bad = edit(text, "share = [0.5, 0.5]", "share = [1.0]")
    err = refuse(bad, r"must be 2 numbers, one per load mass")
    assert err.key == "load.share"


def test_disconnected_graph(text):
    # C57 re-routed to Q4: nothing reaches Q7 any more
    bad = edit(text, 'from = "Q5"\nto = "Q7"', 'from = "Q5"\nto = "Q4"')
    err = refuse(bad, r"the driveline graph is disconnected: masses \['Q7'\] are not linked to "
                      r"'Q1' by any element")
    assert (err.key, err.line) == ("mass[Q7].id", line_of(bad, 'id = "Q7"'))


def test_closed_loop_is_accepted(text):
    # the work rolls meeting through the strip: Q6-Q7 closes the loop Q4-Q5-Q7-Q6-Q4
    loop = edit(text, "[load]", '[[element]]\nid = "C67"\nlabel = "strip"\nfrom = "Q6"\n'
                                 'to = "Q7"\nk = 5.0e8\n\n[load]')
    mill = parse_mill(loop, path=PATH)
    assert mill.element_ids[-1] == "C67"
    assert len(mill.elements) == len(mill.masses)  # one more element than a tree has


@pytest.mark.parametrize("kind", ["soft", "Softening", "bilinear"])
def test_unknown_stiffness_kind(text, kind):
    bad = edit(text, "gap = 0.002\ngap_open = 0.0\nradius = 0.5\n\n[[element]]\nid = \"C57\"",
               f"gap = 0.002\ngap_open = 0.0\nradius = 0.5\nstiffness = \"{kind}\"\n\n"
               f"[[element]]\nid = \"C57\"")
    err = refuse(bad, rf"unknown stiffness kind '{kind}'; expected one of \['linear', "
                      r"'softening', 'hardening'\]")
    assert (err.key, err.line) == ("element[C46].stiffness", line_of(bad, "stiffness = "))


def test_softening_needs_knee_and_smaller_k_after(text):
    base = "gap = 0.0005\ngap_open = 0.0\nradius = 0.25\n"
    bad = edit(text, base, base + 'stiffness = "softening"\nknee = 0.002\n')
    err = refuse(bad, r"stiffness = 'softening' needs 'k_after'")
    assert err.key == "element[C23]" and err.line == line_of(bad, 'id = "C23"') - 1
    bad = edit(text, base, base + 'stiffness = "softening"\nknee = 0.002\nk_after = 9e7\n')
    err = refuse(bad, r"softening needs k_after < k")
    assert (err.key, err.line) == ("element[C23].k_after", line_of(bad, "k_after = 9e7"))
    ok = parse_mill(edit(text, base, base + 'stiffness = "softening"\nknee = 0.002\n'
                                            'k_after = 2e7\n'), path=PATH)
    assert ok.element("C23").stiffness is StiffnessKind.SOFTENING


def test_invalid_toml_names_the_line(text):
    bad = edit(text, "J = 1966.0", "J = = 1966.0")
    err = refuse(bad, r"not valid TOML: .*line \d+")
    assert err.line == line_of(bad, "J = = 1966.0")
    assert err.key is None
    assert str(err).startswith(f"{PATH}:{err.line}: not valid TOML")


@pytest.mark.parametrize("channel, old, new, match", [
    ("T_C12", 'element = "C12"\nunit = "kN*m"', 'element = "C12"\nunit = "g"',
     r"unit 'g' is not a torque unit; expected one of \['N\*m', 'kN\*m', 'MN\*m'\]"),
    ("A_B23_v", 'direction = "vertical"\nunit = "g"\n\n[[channel]]\nname = "A_B23_h"',
     'direction = "vertical"\nunit = "kN*m"\n\n[[channel]]\nname = "A_B23_h"',
     r"unit 'kN\*m' is not a acceleration unit; expected one of \['m/s\^2', 'g'\]"),
])
def test_unit_not_matching_quantity(text, channel, old, new, match):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert err.key == f"channel[{channel}].unit"
    assert err.line == line_of(bad, "unit = ", after=f'name = "{channel}"')


def test_unit_aliases_are_normalised(text):
    mill = parse_mill(edit(text, 'element = "C12"\nunit = "kN*m"', 'element = "C12"\nunit = "kNm"'),
                      path=PATH)
    assert mill.channel("T_C12").unit == "kN*m"


@pytest.mark.parametrize("old, new, match, key, nth", [
    ('id = "Q2"', 'id = "Q1"', r"duplicate mass id 'Q1'", "mass[Q1].id", 2),
    ('id = "C23"', 'id = "C12"', r"duplicate id 'C12'", "element[C12].id", 2),
    ('id = "C23"', 'id = "Q3"', r"duplicate id 'Q3'", "element[Q3].id", 2),
    ('id = "B45"', 'id = "B23"', r"duplicate id 'B23'", "bearing[B23].id", 2),
    ('name = "T_C34"', 'name = "T_C12"', r"duplicate channel name 'T_C12'",
     "channel[T_C12].name", 2),
])
def test_duplicate_ids(text, old, new, match, key, nth):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert err.key == key
    needle = new
    hits = [i + 1 for i, ln in enumerate(bad.splitlines()) if ln.strip() == needle]
    assert err.line == hits[nth - 1]  # the second occurrence is the one refused


def test_misspelled_key_is_refused_not_ignored(text):
    bad = edit(text, "gap_open = 0.0\nradius = 0.35", "Gap_Open = 0.0\nradius = 0.35")
    err = refuse(bad, r"unknown key 'Gap_Open'; did you mean 'gap_open'\?")
    assert (err.key, err.line) == ("element[C12].Gap_Open", line_of(bad, "Gap_Open"))


# mill-config.md: the project "must refuse a file with a key or table it does not know (a
# misspelt optional key would silently lose its value: say which known key was probably
# meant)".  (An earlier reading, "may accept more keys", let any extra key through.)
@pytest.mark.parametrize("old, new, match, key, needle", [
    ("radius = 0.35", "raduis = 0.35", r"unknown key 'raduis'; did you mean 'radius'\?",
     "element[C12].raduis", "raduis"),
    ("[operation]", "[operatoin]", r"unknown table \[operatoin\]; did you mean \[operation\]\?",
     "operatoin", "[operatoin]"),
    ('label = "motor rotor"', 'label = "motor rotor"\nvendor = "x"',
     r"unknown key 'vendor'; expected one of \['J', 'id', 'label'\]", "mass[Q1].vendor",
     "vendor"),
    ("share = [0.5, 0.5]", "share = [0.5, 0.5]\nshares = [1.0]",
     r"unknown key 'shares'; did you mean 'share'\?", "load.shares", "shares ="),
    ("motor_speed_rpm = 180.0", "motor_speed_rpm = 180.0\nmotor_speed = 180.0",
     r"unknown key 'motor_speed'; did you mean 'motor_speed_rpm'\?", "operation.motor_speed",
     "motor_speed ="),
    ("housing_preload = 4.0e5", "housing_prelaod = 4.0e5",
     r"unknown key 'housing_prelaod'; did you mean 'housing_preload'\?",
     "bearing[B23].housing_prelaod", "housing_prelaod"),
    ('unit = "kN*m"\n\n[[channel]]\nname = "T_C34"', 'unit = "kN*m"\nsacle = 2.0\n\n'
     '[[channel]]\nname = "T_C34"', r"unknown key 'sacle'; did you mean 'scale'\?",
     "channel[T_C12].sacle", "sacle"),
    ('[motor]\nmass = "Q1"', '[motor]\nmass = "Q1"\ntorque_limt = 1.0', r"did you mean "
     r"'torque_limit'\?", "motor.torque_limt", "torque_limt"),
    ('[[mass]]\nid = "Q1"', '[[masss]]\nid = "Q0"\nJ = 1.0\n\n[[mass]]\nid = "Q1"',
     r"unknown table \[\[masss\]\]; did you mean \[\[mass\]\]\?", "masss", "[[masss]]"),
    ("[operation]\nmotor_speed_rpm = 180.0", "[operation]\nmotor_speed_rpm = 180.0\n\n"
     "[mill.extra]\nowner = 'x'", r"unknown key 'extra'; expected one of \['description', "
     r"'name'\]", "mill.extra", "[mill.extra]"),
    ("[mill]", "nmae = 'x'\n\n[mill]", r"unknown top-level key 'nmae'", "nmae", "nmae"),
])
def test_unknown_key_or_table_is_refused_with_a_suggestion(text, old, new, match, key, needle):
    bad = edit(text, old, new)
    err = refuse(bad, match)
    assert (err.key, err.line) == (key, line_of(bad, needle))


def test_every_shipped_mill_file_loads(repo_root):
    """Every key the shipped mill files use is known (data/mills/*.toml)."""
    files = sorted((repo_root / "data" / "mills").glob("*.toml"))
    assert files
    for f in files:
        assert load_mill(f).name


# --- variants: with_overrides ---------------------------------------------------------------

def test_with_overrides_changes_one_value(mill):
    wider = mill.with_overrides({"C46.gap": 0.006})
    assert wider.element("C46").gap == 0.006
    assert mill.element("C46").gap == 0.002          # the original is untouched
    assert wider.element("C57") == mill.element("C57")
    assert wider != mill and wider.content_hash() != mill.content_hash()
    assert wider.sha256 != mill.sha256


def test_with_no_overrides_round_trips(mill):
    same = mill.with_overrides({})
    assert same == mill and same.content_hash() == mill.content_hash()


def test_with_overrides_several_tables(mill):
    m = mill.with_overrides({"C23.stiffness": "softening", "C23.knee": 0.002,
                             "C23.k_after": 2.0e7, "Q1.J": 4000.0, "motor.kp": 1.0e5,
                             "operation.motor_speed_rpm": 200.0, "B23.clearance": 1.2e-3,
                             "T_C12.unit": "MN*m", "load.share": [0.6, 0.4]})
    c23 = m.element("C23")
    assert (c23.stiffness, c23.knee, c23.k_after) == (StiffnessKind.SOFTENING, 0.002, 2.0e7)
    assert m.masses[0].J == 4000.0 and m.motor.kp == 1.0e5 and m.motor_speed_rpm == 200.0
    assert m.bearing("B23").clearance == 1.2e-3 and m.channel("T_C12").unit == "MN*m"
    assert m.load.share == (0.6, 0.4)


@pytest.mark.parametrize("overrides, match, key", [
    ({"C99.gap": 0.006}, r"unknown id 'C99' in override 'C99.gap'", "C99.gap"),
    ({"C46.gapp": 0.006}, r"unknown key 'gapp' for a element; expected one of \[.*'gap', "
                          r"'gap_critical', 'gap_open'.*; did you mean 'gap'\?", "C46.gapp"),
    ({"C64.gap": 0.006}, r"unknown id 'C64' in override 'C64.gap'; did you mean 'C46'\?",
     "C64.gap"),
    ({"C46gap": 0.006}, r"override must look like ID.KEY=VALUE. Got 'C46gap'", "C46gap"),
])
def test_with_overrides_refuses_unknown_id_or_key(mill, overrides, match, key):
    with pytest.raises(MillFileError, match=match) as info:
        mill.with_overrides(overrides)
    assert info.value.key == key


@pytest.mark.parametrize("overrides, match, key", [
    ({"C46.gap_open": 0.003}, r"gap_open \(0.003\) must not exceed gap \(0.002\)",
     "element[C46].gap_open"),
    ({"C46.gap": 0.001, "C46.gap_open": 0.0015}, r"gap_open \(0.0015\) must not exceed gap",
     "element[C46].gap_open"),
    ({"Q1.J": 0.0}, r"must be positive. Got 0.0 instead", "mass[Q1].J"),
    ({"C46.to": "Q4"}, r"element joins mass 'Q4' to itself", "element[C46].to"),
    ({"load.share": [0.3, 0.3]}, r"shares must be non-negative and sum to 1", "load.share"),
    ({"C23.stiffness": "springy"}, r"unknown stiffness kind 'springy'", "element[C23].stiffness"),
])
def test_with_overrides_revalidates(mill, overrides, match, key):
    with pytest.raises(MillFileError, match=match) as info:
        mill.with_overrides(overrides)
    assert info.value.key == key
