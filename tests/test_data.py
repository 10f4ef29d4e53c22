"""difftissue.data: loaders on the two bundled real files and on broken variants of them.

Reference numbers were read by hand from the files (first/last rows, header entries).
Broken variants are written to ``tmp_path`` by the tests themselves.
"""

import hashlib
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from docblocks import assert_doctests_pass

import difftissue as dt
from difftissue import data as dd
from difftissue import errors as E

ROOT = Path(__file__).resolve().parents[1]
CHIARO = ROOT / "data" / "afm" / "chiaro_AEBP1_indentation_002.txt"
INSTRON = ROOT / "data" / "compression" / "EF10_50T_A1.csv"


@pytest.fixture(scope="module")
def chiaro():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the real file must load without any warning
        return dd.load_chiaro(CHIARO)


@pytest.fixture(scope="module")
def contact(chiaro):
    return dd.find_contact(chiaro)


@pytest.fixture(scope="module")
def instron():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return dd.load_instron_compression(INSTRON)


def _chiaro_lines() -> list[bytes]:
    return re.split(rb"\r\n|\r|\n", CHIARO.read_bytes())


def _write(path: Path, data) -> Path:
    if isinstance(data, str):
        data = data.encode("utf-8")
    path.write_bytes(data)
    return path


# ================================================================ Chiaro (AFM) file
def test_chiaro_file_properties(chiaro):
    m = chiaro.metadata
    assert m["format"] == "chiaro-txt"
    assert m["encoding"] == "latin-1"  # byte 0xB5 (µ) is not UTF-8
    assert m["line_endings"] == {"CRLF": 13858, "LF": 6, "CR": 1}
    assert m["sha256"] == hashlib.sha256(CHIARO.read_bytes()).hexdigest()
    assert m["source"] == str(CHIARO)
    assert m["header_line"] == 38
    assert m["units"] == {"time": "s", "force": "uN", "indentation": "nm", "cantilever": "nm", "piezo": "nm", "auxiliary": "-"}
    assert m["columns"]["force"] == "Load (uN)"
    assert set(m["signs"].values()) == {1}  # load and indentation are already positive into the sample


def test_chiaro_header(chiaro):
    inst = chiaro.metadata["instrument"]
    assert inst["tip_radius"] == pytest.approx(27.5e-6)
    assert inst["cantilever_stiffness"] == pytest.approx(0.019)
    assert inst["calibration_factor"] == pytest.approx(2.809)
    assert inst["effective_modulus"] == pytest.approx(156.009)
    assert inst["youngs_modulus"] == pytest.approx(117.007)
    assert inst["poisson_ratio_assumed"] == 0.5
    assert inst["max_load_setpoint"] == pytest.approx(0.050e-6)  # "Max load (µN)" in Latin-1
    assert inst["piezo_speed"] == pytest.approx(7.0e-6)
    assert inst["peak_load"] == pytest.approx(0.049e-6)
    assert inst["z_surface"] == pytest.approx(6838.680e-6)
    assert (inst["device"], inst["software_version"], inst["model"], inst["name"]) == ("Chiaro", "V3.5.0", "Hertz", "AEBP1_01")
    assert inst["control_mode"] == "Peak Load Poking"
    assert chiaro.metadata["header"]["SMDuration (s)"] == "0.000"


def test_chiaro_values(chiaro):
    assert len(chiaro) == 13827
    # first row: 0.000000  -0.000308  0.000000  -16.214418  64.971622  -0.002890
    assert chiaro.time[0] == 0.0
    assert chiaro.force[0] == pytest.approx(-0.000308e-6)
    assert chiaro.channels["cantilever"][0] == pytest.approx(-16.214418e-9)
    assert chiaro.channels["piezo"][0] == pytest.approx(64.971622e-9)
    assert chiaro.depth[0] == pytest.approx((64.971622 + 16.214418) * 1e-9)  # piezo - cantilever
    assert chiaro.channels["auxiliary"][0] == pytest.approx(-0.002890)
    # last row: 13.826000  -0.000315  0.000000  -16.590636  54.932839  -0.003273
    assert chiaro.time[-1] == pytest.approx(13.826)
    assert chiaro.force[-1] == pytest.approx(-0.000315e-6)
    assert chiaro.depth[-1] == pytest.approx((54.932839 + 16.590636) * 1e-9)
    # peak load 0.049240 uN at t = 12.663 s; piezo turns round at sample 12664 (88079.73 nm)
    assert chiaro.force.max() == pytest.approx(0.04924e-6)
    assert chiaro.time[np.argmax(chiaro.force)] == pytest.approx(12.663)
    assert chiaro.turnaround_index == 12664
    assert chiaro.channels["piezo"].max() == pytest.approx(88079.73462e-9)
    # the load is k times the cantilever deflection; the instrument's indentation is
    # piezo - cantilever - 73078.91 nm after its contact point (sample 10526, t = 10.526 s)
    assert chiaro.metadata["checks"]["load_over_k_deflection"] == pytest.approx(1.0, abs=1e-4)
    assert chiaro.metadata["instrument"]["contact_index"] == 10526
    assert chiaro.metadata["instrument"]["contact_depth"] == pytest.approx(73078.9116e-9, abs=1e-12)
    assert chiaro.channels["instrument_indentation"].max() == pytest.approx(12969.951949e-9)


def test_chiaro_instrument_depth():
    c = dd.load_chiaro(CHIARO, depth="instrument")
    assert c.depth.max() == pytest.approx(12969.951949e-9)
    assert np.all(c.depth[:10526] == 0.0) and c.depth[10526] > 0
    assert c.turnaround_index == 12664


def test_approach_segment(chiaro):
    a = chiaro.approach()
    assert len(a) == 12665
    assert a.time[-1] == pytest.approx(12.664)
    assert a.metadata["segment"] == "approach"
    assert len(a.metadata["data_lines"]) == len(a)
    assert a.channels["piezo"].shape == a.depth.shape


# ================================================================ contact point
def test_contact_power_law_on_real_curve(chiaro, contact):
    inst = chiaro.metadata["instrument"]["contact_depth"]
    assert contact.method == "power_law"
    # the fit finds contact within ~0.5 um of the instrument's own contact (73.08 um of raw depth)
    assert abs(contact.depth - inst) < 1.0e-6
    assert 10400 < contact.index < 10700
    assert 1.3 < contact.exponent < 1.6  # close to the Hertz exponent of a sphere, not imposed
    lo, hi = contact.interval
    assert lo <= contact.depth <= hi and hi - lo < 3e-6
    assert abs(contact.force) < 2e-9 and 0 < contact.rms < 1e-9
    assert contact.to_dict()["method"] == "power_law"


def test_contact_other_methods(chiaro):
    hertz = dd.find_contact(chiaro, exponent=1.5)
    assert hertz.exponent == 1.5
    assert hertz.depth == pytest.approx(73.28e-6, abs=0.3e-6)
    inst = dd.find_contact(chiaro, method="instrument")
    assert inst.depth == pytest.approx(73078.9116e-9, abs=1e-12) and inst.index == 10526
    rov = dd.find_contact(chiaro, method="ratio_of_variances")
    assert 0 <= rov.index <= chiaro.turnaround_index + 1
    with pytest.raises(E.ContactPointError, match="unknown contact method"):
        dd.find_contact(chiaro, method="threshold")


def test_shift_to_contact_real_curve(chiaro, contact):
    s = dd.shift_to_contact(chiaro, contact)
    assert s.depth[0] >= 0 and s.depth[0] < 50e-9
    assert np.all(s.depth > 0)
    assert 11.5e-6 < s.depth.max() < 13.0e-6  # instrument: 12.97 um from its own contact
    assert s.force.max() == pytest.approx(0.04924e-6, abs=2e-9)
    assert s.time[-1] == pytest.approx(12.664)  # approach only
    assert len(s) == chiaro.turnaround_index + 1 - contact.index
    assert s.metadata["contact"]["depth"] == contact.depth
    assert s.metadata["instrument"]["tip_radius"] == pytest.approx(27.5e-6)
    # the raw depth steps back by up to ~22 nm (cantilever noise) even after contact
    with pytest.raises(E.NonMonotonicError, match="largest step back is 2.*e-08 m") as info:
        dd.shift_to_contact(chiaro, contact, monotonic=True)
    assert info.value.rows and info.value.lines[0] > 10000
    dd.shift_to_contact(chiaro, contact, monotonic=True, monotonic_tolerance=30e-9)
    full = dd.shift_to_contact(chiaro, contact, keep_precontact=True, baseline="offset")
    assert len(full) == chiaro.turnaround_index + 1 and full.depth[0] < -70e-6


def _synthetic(p, *, n=3000, z0=14e-6, noise=2e-10, seed=0):
    rng = np.random.default_rng(seed)
    z = np.linspace(0.0, 20e-6, n)
    f = 2e-10 + 1e-5 * z + 1e-9 * np.clip((z - z0) / 1e-6, 0, None) ** p + rng.normal(0, noise, n)
    return dd.ForceDepthCurve(z, f, np.arange(n) * 1e-3)


@pytest.mark.parametrize("p", [1.0, 1.5, 2.0])
def test_contact_synthetic(p):
    c = dd.find_contact(_synthetic(p))
    assert c.depth == pytest.approx(14e-6, abs=0.1e-6)
    assert c.exponent == pytest.approx(p, abs=0.15)
    assert c.baseline_slope == pytest.approx(1e-5, rel=0.2)
    s = dd.shift_to_contact(_synthetic(p), c)
    assert s.depth.max() == pytest.approx(6e-6, abs=0.1e-6)


def test_contact_errors():
    flat = dd.ForceDepthCurve(np.linspace(0, 1e-6, 200), np.random.default_rng(1).normal(0, 1e-10, 200))
    with pytest.raises(E.ContactPointError, match="not clearly above the baseline noise"):
        dd.find_contact(flat)
    with pytest.raises(E.ContactPointError, match="at least 20"):
        dd.find_contact(dd.ForceDepthCurve([0, 1e-6, 2e-6], [0, 0, 1e-9]))
    with pytest.raises(E.ContactPointError, match="no instrument contact"):
        dd.find_contact(_synthetic(1.5), method="instrument")


# ================================================================ Chiaro variants
def test_chiaro_utf8_copy_and_line_endings(tmp_path, chiaro):
    text = CHIARO.read_bytes().decode("latin-1")
    lines = re.split(r"\r\n|\r|\n", text)
    variants = {
        "utf8.txt": ("utf-8", text.encode("utf-8")),
        "utf8bom.txt": ("utf-8-sig", b"\xef\xbb\xbf" + text.encode("utf-8")),
        "crlf.txt": ("latin-1", "\r\n".join(lines).encode("latin-1")),
        "cr.txt": ("latin-1", "\r".join(lines).encode("latin-1")),
        "lf.txt": ("latin-1", "\n".join(lines).encode("latin-1")),
    }
    for name, (encoding, data) in variants.items():
        c = dd.load_chiaro(_write(tmp_path / name, data))
        assert c.metadata["encoding"] == encoding, name
        np.testing.assert_array_equal(c.force, chiaro.force)
        np.testing.assert_array_equal(c.depth, chiaro.depth)
        assert c.metadata["instrument"]["max_load_setpoint"] == pytest.approx(0.05e-6)  # "µN" decoded right
        assert c.metadata["instrument"]["tip_radius"] == pytest.approx(27.5e-6)
    cr = dd.load_chiaro(tmp_path / "cr.txt")
    assert cr.metadata["line_endings"]["CR"] > 13000 and cr.metadata["line_endings"]["CRLF"] == 0
    # decoding the UTF-8 copy as Latin-1 garbles µ into "Âµ": the micro unit is then unknown
    with pytest.raises(E.UnitError, match="unknown unit"):
        dd.unit_factor("Âµm", "length")


def test_chiaro_truncated_header(tmp_path):
    lines = _chiaro_lines()
    with pytest.raises(E.HeaderError, match=r"ends inside the metadata header \(truncated\?\)"):
        dd.load_chiaro(_write(tmp_path / "t.txt", b"\r\n".join(lines[:11])))
    no_tip = [line for line in lines if not line.startswith(b"Tip radius")]
    with pytest.raises(E.HeaderError, match=r"no 'Tip radius \(um\)' entry"):
        dd.load_chiaro(_write(tmp_path / "tip.txt", b"\r\n".join(no_tip)))
    no_k = [line for line in lines if not line.startswith(b"k (N/m)")]
    with pytest.raises(E.HeaderError, match=r"'k \(N/m\)'"):
        dd.load_chiaro(_write(tmp_path / "k.txt", b"\r\n".join(no_k)))


def test_chiaro_broken_rows(tmp_path):
    lines = _chiaro_lines()
    cut = b"\r\n".join(lines[:-2]) + b"\r\n13.825000\t-0.0003"
    with pytest.raises(E.MalformedDataError, match=r"line 13865 .* 2 field\(s\) but the header has 6") as info:
        dd.load_chiaro(_write(tmp_path / "cut.txt", cut))
    assert info.value.lines == (13865,)
    nan = list(lines)
    fields = nan[100].split(b"\t")
    fields[1] = b"nan"
    nan[100] = b"\t".join(fields)
    with pytest.raises(E.NonFiniteDataError, match=r"column 'Load \(uN\)' at data rows \[62\] \(file lines \[101\]\)") as info:
        dd.load_chiaro(_write(tmp_path / "nan.txt", b"\r\n".join(nan)))
    assert info.value.rows == (62,)
    text = list(lines)
    text[200] = text[200].replace(b"\t", b"\tabc\t", 1)
    with pytest.raises(E.MalformedDataError, match="cannot read a number from 'abc'"):
        dd.load_chiaro(_write(tmp_path / "abc.txt", b"\r\n".join(text)))


@pytest.mark.parametrize(
    "old, new, error, match",
    [
        (b"Load (uN)", b"Load (N)", E.ImplausibleMagnitudeError, r"force .*0.04924 N, above the plausible range \[1e-13, 1e-03\] N .*'mN' or 'uN' or 'nN'"),
        (b"Piezo (nm)", b"Piezo (m)", E.ImplausibleMagnitudeError, r"8.808e\+04 m, above the plausible range .*'nm'"),
        (b"Load (uN)", b"Load (lbf)", E.UnitError, r"unknown unit 'lbf' in the column name; .*kN, N, mN, uN, nN, pN"),
        (b"Piezo (nm)", b"Z (nm)", E.MissingColumnError, r"no 'Piezo \(nm\)' column .*'Z \(nm\)'"),
    ],
)
def test_chiaro_column_variants(tmp_path, old, new, error, match):
    lines = _chiaro_lines()
    assert old in lines[37]
    lines[37] = lines[37].replace(old, new)
    with pytest.raises(error, match=match):
        dd.load_chiaro(_write(tmp_path / "v.txt", b"\r\n".join(lines)))


def test_chiaro_inconsistent_stiffness_warns(tmp_path):
    lines = [line.replace(b"k (N/m)\t0.019", b"k (N/m)\t0.038") for line in _chiaro_lines()]
    with pytest.warns(E.InconsistentDataWarning, match="0.5 x k"):
        c = dd.load_chiaro(_write(tmp_path / "k2.txt", b"\r\n".join(lines)))
    assert c.metadata["instrument"]["cantilever_stiffness"] == pytest.approx(0.038)


# ================================================================ Instron compression file
def test_instron_header(instron):
    m = instron.metadata
    assert m["format"] == "instron-csv" and m["encoding"] == "utf-8"
    assert m["line_endings"] == {"CRLF": 0, "LF": 1210, "CR": 0}
    assert m["sha256"] == hashlib.sha256(INSTRON.read_bytes()).hexdigest()
    inst = m["instrument"]
    assert inst["sample"] == "EF10_50T_A_sample_1" and inst["test"] == "Compression test"
    assert inst["machine"] == "INSTRON 5900"
    assert inst["load_cell_capacity"] == 1000.0
    assert inst["speed"] == pytest.approx(10e-3 / 60)
    assert instron.diameter == pytest.approx(0.050) and instron.height == pytest.approx(0.030)
    assert instron.area == pytest.approx(math.pi * 0.05**2 / 4)
    assert m["header_line"] == 8
    # compression and load are positive in the file; strains and stresses negative
    assert m["signs"] == {"time": 1, "displacement": 1, "force": 1, "strain": -1, "stress": -1, "true_strain": -1, "true_stress": -1}
    assert m["units"]["stress"] == "kPa" and m["units"]["displacement"] == "mm"


def test_instron_values(instron):
    assert len(instron) == 1202
    # first row: 0.000000,0.000000,0.000610,-0.000000,-0.000311,0.000000,-0.000311
    assert instron.force[0] == pytest.approx(0.00061)
    assert instron.stress[0] == pytest.approx(0.311)
    assert instron.strain[0] == 0.0
    # second row: 0.100000,0.007250,0.021890,-0.000242,-0.011148,-0.000242,-0.011146
    assert instron.displacement[1] == pytest.approx(7.25e-6)
    assert instron.strain[1] == pytest.approx(0.000242)
    # last row: 120.021000,20.000060,152.676500,-0.666669,-77.757503,-1.098618,-25.919012
    assert instron.time[-1] == pytest.approx(120.021)
    assert instron.displacement[-1] == pytest.approx(0.02000006)
    assert instron.force[-1] == pytest.approx(152.6765)
    assert instron.strain[-1] == pytest.approx(0.666669)
    assert instron.stress[-1] == pytest.approx(77757.503)
    assert instron.true_strain[-1] == pytest.approx(1.098618)
    assert instron.true_stress[-1] == pytest.approx(25919.012)
    assert instron.strain.max() == pytest.approx(0.667, abs=1e-3)  # ~67 % peak strain
    assert np.all(np.diff(instron.displacement) > 0)  # loading only, strictly monotonic
    assert len(instron.loading()) == len(instron)


def test_instron_internal_consistency(instron):
    checks = instron.metadata["checks"]
    # stress = load / (pi 25^2 mm^2) and strain = compression / 30 mm to the file's rounding
    assert checks["stress_vs_force_over_area"]["max_deviation_rel_to_peak"] < 1e-6
    assert checks["strain_vs_displacement_over_height"]["max_deviation_rel_to_peak"] < 1e-5
    # true strain = -ln(1 - eps); true stress = sigma (1 - eps): incompressible Cauchy stress
    assert checks["true_strain_vs_minus_log_1_minus_strain"]["ok"]
    assert checks["true_stress_vs_stress_times_1_minus_strain"]["ok"]
    assert checks["speed_ratio"] == pytest.approx(1.0, abs=1e-4)
    assert checks["peak_load_over_capacity"] == pytest.approx(0.1526765)
    np.testing.assert_allclose(instron.stress, instron.force / instron.area, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(instron.strain, instron.displacement / instron.height, atol=1e-6)


def test_instron_wrong_diameter(tmp_path, instron):
    p = _write(tmp_path / "d40.csv", INSTRON.read_text().replace("Diameter: 50mm", "Diameter: 40mm"))
    with pytest.raises(E.InconsistentDataError, match=r"stress column .*header diameter = 40 mm.*implies a diameter of 50 mm"):
        dd.load_instron_compression(p)
    with pytest.warns(E.InconsistentDataWarning, match="implies a diameter of 50 mm"):
        c = dd.load_instron_compression(p, consistency="warn")
    assert c.diameter == pytest.approx(0.04)
    np.testing.assert_allclose(c.stress, instron.stress)  # the file's stresses are kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dd.load_instron_compression(p, consistency="ignore")


def test_instron_wrong_height(tmp_path):
    p = _write(tmp_path / "h25.csv", INSTRON.read_text().replace("Height: 30mm", "Height: 25mm"))
    with pytest.raises(E.InconsistentDataError, match="implies a height of 30 mm"):
        dd.load_instron_compression(p)


def test_instron_variants(tmp_path, instron):
    text = INSTRON.read_text()
    lines = text.splitlines()
    crlf = dd.load_instron_compression(_write(tmp_path / "crlf.csv", "\r\n".join(lines) + "\r\n"))
    assert crlf.metadata["line_endings"]["CRLF"] == 1210
    np.testing.assert_array_equal(crlf.stress, instron.stress)
    # a file that writes compression and load negative gives the same (positive) curve
    neg = lines[:8] + [",".join(("-" + x if i in (1, 2) else x) for i, x in enumerate(row.split(","))) for row in lines[8:]]
    c = dd.load_instron_compression(_write(tmp_path / "neg.csv", "\n".join(neg)))
    assert c.metadata["signs"]["displacement"] == -1 and c.metadata["signs"]["force"] == -1
    np.testing.assert_allclose(c.displacement, instron.displacement)
    np.testing.assert_allclose(c.force, instron.force)
    with pytest.raises(E.HeaderError, match="no diameter entry"):
        dd.load_instron_compression(_write(tmp_path / "nod.csv", text.replace("Cylinder Diameter: 50mm;\n", "")))
    with pytest.raises(E.HeaderError, match="no column row .* truncated"):
        dd.load_instron_compression(_write(tmp_path / "tr.csv", "\n".join(lines[:5])))
    with pytest.raises(E.MissingColumnError, match=r"no Load column.*'Weight \(N\)'") as info:
        dd.load_instron_compression(_write(tmp_path / "w.csv", text.replace("Load (N)", "Weight (N)")))
    assert "Weight (N)" in info.value.available
    row = lines[20].split(",")
    row[2] = "nan"
    nan = lines[:20] + [",".join(row)] + lines[21:]
    with pytest.raises(E.NonFiniteDataError, match=r"data rows \[12\] \(file lines \[21\]\)"):
        dd.load_instron_compression(_write(tmp_path / "nan.csv", "\n".join(nan)))
    with pytest.raises(E.EmptyDataError):
        dd.load_instron_compression(_write(tmp_path / "empty.csv", "\n \n"))


# ================================================================ generic CSV/TSV loader
CURVE = "# bench indenter, run 3\nDepth (mm),Force (N),Time (s)\n0,0.001,0\n0.1,0.5,1\n0.2,1.5,2\n0.3,3.0,3\n0.2,1.2,4\n"


def test_generic_force_depth(tmp_path):
    p = _write(tmp_path / "c.csv", CURVE)
    c = dd.load_force_depth({"path": str(p), "columns": {"depth": "Depth (mm)", "force": {"name": "Force (N)", "sign": -1}, "time": "Time (s)"}, "plausible": {"force": (1e-7, 1e5)}})
    np.testing.assert_allclose(c.depth, [0, 1e-4, 2e-4, 3e-4, 2e-4])
    np.testing.assert_allclose(c.force, [-0.001, -0.5, -1.5, -3.0, -1.2])
    assert c.metadata["header_line"] == 2 and c.metadata["preamble"] == ["# bench indenter, run 3"]
    assert c.metadata["signs"] == {"depth": 1, "force": -1, "time": 1}
    assert c.turnaround_index == 3 and len(c.approach()) == 4
    # relative path with base_dir; monotonic loading holds (the last row is unloading)
    c2 = dd.load_force_depth({"path": "c.csv", "columns": {"depth": "Depth (mm)", "force": "Force (N)"}, "monotonic": True}, base_dir=tmp_path)
    np.testing.assert_allclose(c2.force, -c.force)


def test_generic_tsv_latin1_semicolon_decimal_comma(tmp_path):
    body = "Instrument: bench\r\nIndentation (µm)\tLoad (mN)\r\n0\t0\r\n5\t1.5\r\n10\t4.0\r\n"
    p = _write(tmp_path / "l1.tsv", body.encode("latin-1"))
    c = dd.load_force_depth({"path": str(p), "columns": {"depth": "Indentation (µm)", "force": "Load (mN)"}})
    assert c.metadata["encoding"] == "latin-1" and c.metadata["delimiter"] == "\t"
    assert c.metadata["units"] == {"depth": "µm", "force": "mN"}
    np.testing.assert_allclose(c.depth, [0, 5e-6, 10e-6])
    np.testing.assert_allclose(c.force, [0, 1.5e-3, 4e-3])
    u = _write(tmp_path / "u8.tsv", body.encode("utf-8"))
    c8 = dd.load_force_depth({"path": str(u), "columns": {"depth": "Indentation (um)", "force": "Load (mN)"}})  # µ and u match
    assert c8.metadata["encoding"] == "utf-8"
    np.testing.assert_array_equal(c8.depth, c.depth)
    eu = _write(tmp_path / "eu.csv", "Tiefe (mm);Kraft (N)\n0;0\n0,5;1,25\n1,0;2,5\n")
    ce = dd.load_force_depth({"path": str(eu), "decimal": ",", "columns": {"depth": "Tiefe (mm)", "force": "Kraft (N)"}})
    assert ce.metadata["delimiter"] == ";"
    np.testing.assert_allclose(ce.force, [0, 1.25, 2.5])
    with pytest.raises(E.MalformedDataError, match="decimal commas"):
        dd.load_force_depth({"path": str(eu), "delimiter": ";", "columns": {"depth": "Tiefe (mm)", "force": "Kraft (N)"}})
    mixed = _write(tmp_path / "mixed.csv", b"Depth (mm),Force (N)\r\n0,0\n0.1,0.5\r0.2,1.5\r\n")
    cm = dd.load_force_depth({"path": str(mixed), "columns": {"depth": "Depth (mm)", "force": "Force (N)"}})
    assert cm.metadata["line_endings"] == {"CRLF": 2, "LF": 1, "CR": 1}
    np.testing.assert_allclose(cm.depth, [0, 1e-4, 2e-4])


def test_generic_headerless_by_index(tmp_path):
    p = _write(tmp_path / "raw.txt", "0 0\n100 0.2\n200 0.9\n")
    c = dd.load_force_depth({"path": str(p), "header_line": False, "delimiter": None, "regime": "afm", "columns": {"depth": {"index": 0, "unit": "nm"}, "force": {"index": 1, "unit": "nN"}}})
    np.testing.assert_allclose(c.depth, [0, 1e-7, 2e-7])
    np.testing.assert_allclose(c.force, [0, 0.2e-9, 0.9e-9])
    with pytest.raises(E.DataError, match="needs columns by 'index'"):
        dd.load_force_depth({"path": str(p), "header_line": False, "columns": {"depth": "a", "force": "b"}})


def test_generic_errors(tmp_path):
    p = _write(tmp_path / "c.csv", CURVE)
    cols = {"depth": "Depth (mm)", "force": "Force (N)"}
    with pytest.raises(E.MissingColumnError, match=r"column 'Load \(N\)' not found .*\['Depth \(mm\)', 'Force \(N\)', 'Time \(s\)'\]") as info:
        dd.load_force_depth({"path": str(p), "columns": {"depth": "Depth (mm)", "force": "Load (N)"}})
    assert info.value.column == "Load (N)" and info.value.available == ("Depth (mm)", "Force (N)", "Time (s)")
    with pytest.raises(E.UnitError, match="declared in 'm' but its name says 'mm'"):
        dd.load_force_depth({"path": str(p), "columns": {"depth": {"name": "Depth (mm)", "unit": "m"}, "force": "Force (N)"}})
    with pytest.raises(E.UnitError, match="unknown unit 'furlong'.*m, cm, mm, um, nm"):
        dd.load_force_depth({"path": str(p), "columns": {"depth": {"name": "Depth (mm)", "unit": "furlong", "override_header_unit": True}, "force": "Force (N)"}})
    with pytest.raises(E.UnitError, match="measures pressure, not force"):
        dd.load_force_depth({"path": str(p), "columns": {"depth": "Depth (mm)", "force": {"name": "Force (N)", "unit": "kPa", "override_header_unit": True}}})
    with pytest.raises(E.NonMonotonicError, match=r"data rows \[2\] \(file lines \[4\]\)"):
        bad = _write(tmp_path / "nm.csv", "Depth (mm),Force (N)\n0,0\n0.2,1\n0.1,1.5\n0.3,3\n")
        dd.load_force_depth({"path": str(bad), "columns": cols, "monotonic": True})
    dd.load_force_depth({"path": str(bad), "columns": cols, "monotonic": True, "monotonic_tolerance": 0.2e-3})
    with pytest.raises(E.DataError, match=r"unknown table config keys \['colums'\]"):
        dd.load_force_depth({"path": str(p), "colums": cols})
    with pytest.raises(E.DataError, match="no such file"):
        dd.load_force_depth({"path": str(tmp_path / "none.csv"), "columns": cols})


def test_generic_nonfinite_rows(tmp_path):
    p = _write(tmp_path / "n.csv", "Depth (mm),Force (N)\n0,0\n0.1,\n0.2,inf\n0.3,NaN\n")
    with pytest.raises(E.NonFiniteDataError, match=r"column 'Force \(N\)' at data rows \[1, 2, 3\] \(file lines \[3, 4, 5\]\)") as info:
        dd.load_force_depth({"path": str(p), "columns": {"depth": "Depth (mm)", "force": "Force (N)"}})
    assert info.value.rows == (1, 2, 3) and info.value.lines == (3, 4, 5)


def test_generic_empty_files(tmp_path):
    cols = {"depth": "Depth (mm)", "force": "Force (N)"}
    with pytest.raises(E.EmptyDataError, match="is empty"):
        dd.load_force_depth({"path": str(_write(tmp_path / "e.csv", "")), "columns": cols})
    with pytest.raises(E.EmptyDataError, match="no data rows"):
        dd.load_force_depth({"path": str(_write(tmp_path / "h.csv", "Depth (mm),Force (N)\n\n")), "columns": cols})
    with pytest.raises(E.EmptyDataError, match="no column names .* no numeric rows"):
        dd.load_force_depth({"path": str(_write(tmp_path / "t.csv", "some title\nanother line\n")), "columns": cols})


def test_plausibility_ranges(tmp_path):
    # depths of 1e5 "m": the values are nanometres
    p = _write(tmp_path / "m.csv", "Depth (m),Force (N)\n0,0\n50000,0.4\n100000,1\n")
    with pytest.raises(E.ImplausibleMagnitudeError, match=r"depth .*1e\+05 m, above the plausible range \[1e-07, 2e-01\] m for 'macro' data; .*'um' or 'nm'"):
        dd.load_force_depth({"path": str(p), "columns": {"depth": "Depth (m)", "force": "Force (N)"}})
    # forces of 1e3 N for an AFM curve declared in N
    q = _write(tmp_path / "afm.csv", "Depth (nm),Force (N)\n0,0\n500,400\n1000,1000\n")
    with pytest.raises(E.ImplausibleMagnitudeError, match=r"force .*1000 N, above the plausible range \[1e-13, 1e-03\] N for 'afm' data"):
        dd.load_force_depth({"path": str(q), "regime": "afm", "columns": {"depth": "Depth (nm)", "force": "Force (N)"}})
    c = dd.load_force_depth({"path": str(q), "regime": "afm", "plausible": {"force": (0, 1e4)}, "columns": {"depth": "Depth (nm)", "force": "Force (N)"}})
    assert c.force.max() == 1000.0
    c = dd.load_force_depth({"path": str(q), "regime": None, "columns": {"depth": "Depth (nm)", "force": "Force (N)"}})
    assert dd.PLAUSIBLE_RANGES["afm"]["depth"] == (1e-10, 1e-3)


def test_generic_compression_matches_instron(instron):
    cols = {
        "time": "Time (s)",
        "displacement": "Compression (mm)",
        "force": "Load (N)",
        "strain": {"name": "Engineering Strain [-]", "sign": -1},
        "stress": {"name": "Engineering Stress (kPa)", "sign": "auto"},
    }
    c = dd.load_compression({"path": str(INSTRON), "columns": cols, "diameter": "50 mm", "height": {"value": 30, "unit": "mm"}, "monotonic": True})
    np.testing.assert_array_equal(c.stress, instron.stress)
    np.testing.assert_array_equal(c.strain, instron.strain)
    assert c.metadata["header_line"] == 8 and c.true_strain is None
    with pytest.raises(E.InconsistentDataError, match="implies a height of 30 mm"):
        dd.load_compression({"path": str(INSTRON), "columns": cols, "diameter": "50 mm", "height": "20 mm"})
    only = {"displacement": "Compression (mm)", "force": "Load (N)"}
    d = dd.load_compression({"path": str(INSTRON), "columns": only, "diameter": 0.05, "height": "30mm"})
    np.testing.assert_allclose(d.stress, instron.stress, rtol=1e-3, atol=1e-3)
    with pytest.raises(E.DataError, match="needs a 'strain' column, or 'displacement' and the specimen 'height'"):
        dd.load_compression({"path": str(INSTRON), "columns": only})
    with pytest.raises(E.ImplausibleMagnitudeError, match=r"diameter \(config value '50 m'\)"):
        dd.load_compression({"path": str(INSTRON), "columns": only, "diameter": "50 m", "height": "30 mm"})


def test_percent_strain_declared_dimensionless(tmp_path):
    p = _write(tmp_path / "pct.csv", "Strain [-],Stress (kPa)\n0,0\n33.3,10\n66.7,40\n")
    with pytest.raises(E.ImplausibleMagnitudeError, match=r"strain .*66.7 -, above the plausible range \[1e-05, 1e\+00\] - .*'%'"):
        dd.load_compression({"path": str(p), "columns": {"strain": "Strain [-]", "stress": "Stress (kPa)"}})
    c = dd.load_compression({"path": str(p), "columns": {"strain": {"name": "Strain [-]", "unit": "%", "override_header_unit": True}, "stress": "Stress (kPa)"}})
    assert c.strain.max() == pytest.approx(0.667) and c.force is None and c.area is None


def test_units_and_quantities():
    assert dd.parse_quantity("50mm", "length") == pytest.approx(0.05)
    assert dd.parse_quantity("27.5 µm", "length") == pytest.approx(27.5e-6)
    assert dd.parse_quantity("1kN", "force") == 1000.0
    assert dd.parse_quantity((10, "mm/min"), "speed") == pytest.approx(1e-3 / 6)
    assert dd.unit_factor("μN", "force") == 1e-6  # Greek mu
    assert dd.unit_factor("%", "strain") == 0.01
    with pytest.raises(E.UnitError, match="measures length, not force"):
        dd.parse_quantity("3 mm", "force")
    with pytest.raises(E.DataError, match="cannot read a number"):
        dd.parse_quantity("fifty mm", "length")


# ================================================================ meshio FEM results
def test_fem_result(tmp_path):
    mesh = dt.block(1e-2, 2)
    u = np.zeros((mesh.n_nodes, 3))
    u[:, 2] = -0.1 * mesh.points[:, 2]
    dt.write_mesh(tmp_path / "r.vtu", mesh, point_data={"displacement": u, "temperature": u[:, 0]})
    r = dd.load_fem_result(tmp_path / "r.vtu")
    np.testing.assert_allclose(r.displacement, u)
    np.testing.assert_allclose(r.deformed_points, mesh.points + u)
    assert r.metadata["field"] == "displacement" and r.metadata["max_displacement"] == pytest.approx(1e-3)
    mm = dd.load_fem_result(tmp_path / "r.vtu", displacement_unit="mm")
    np.testing.assert_allclose(mm.displacement, u * 1e-3)
    dt.write_mesh(tmp_path / "d.vtu", mesh, point_data={"disp": u})
    with pytest.raises(E.MissingFieldError, match=r"no point field 'displacement'; its point fields are: \['disp'\]"):
        dd.load_fem_result(tmp_path / "d.vtu")
    assert dd.load_fem_result(tmp_path / "d.vtu", field="disp").displacement.shape == (27, 3)
    dt.write_mesh(tmp_path / "2d.vtu", mesh, point_data={"displacement": u[:, :2]})
    with pytest.raises(E.MissingFieldError, match=r"shape \(27, 2\); a displacement needs \(27, 3\)"):
        dd.load_fem_result(tmp_path / "2d.vtu")
    bad = u.copy()
    bad[3, 1] = np.nan
    dt.write_mesh(tmp_path / "nan.vtu", mesh, point_data={"displacement": bad})
    with pytest.raises(E.NonFiniteDataError, match=r"nodes \[3\]"):
        dd.load_fem_result(tmp_path / "nan.vtu")
    big = dt.block(10.0, 1)
    dt.write_mesh(tmp_path / "mm.vtu", big, point_data={"displacement": np.full((big.n_nodes, 3), 2.0)})
    assert dd.load_fem_result(tmp_path / "mm.vtu", length_unit="mm").displacement[0, 0] == pytest.approx(2e-3)
    with pytest.raises(E.ImplausibleMagnitudeError, match="another unit than the coordinates"):
        dd.load_fem_result(tmp_path / "mm.vtu", length_unit="mm", displacement_unit="m")


# ================================================================ dispatch, pytrees
def test_load_dataset(tmp_path):
    s = dd.load_dataset({"format": "chiaro", "path": "afm/chiaro_AEBP1_indentation_002.txt", "contact": True, "exponent": 1.5}, base_dir=ROOT / "data")
    assert s.metadata["contact"]["exponent"] == 1.5 and s.depth[0] >= 0
    c = dd.load_dataset({"format": "instron", "path": str(INSTRON), "consistency": "warn"})
    assert isinstance(c, dd.CompressionCurve)
    t = dd.load_dataset({"kind": "force_depth", "path": str(_write(tmp_path / "c.csv", CURVE)), "columns": {"depth": "Depth (mm)", "force": "Force (N)"}})
    assert isinstance(t, dd.ForceDepthCurve)
    with pytest.raises(E.DataError, match=r"unknown keys \['tip'\] for format 'instron'"):
        dd.load_dataset({"format": "instron", "path": str(INSTRON), "tip": 1})
    with pytest.raises(E.DataError, match="unknown dataset format"):
        dd.load_dataset({"format": "xls", "path": "x"})


def test_datasets_are_pytrees(instron):
    import equinox as eqx
    import jax.numpy as jnp

    curve = _synthetic(1.5)
    f = eqx.filter_jit(lambda c, e: jnp.sum((c.force - e * c.depth) ** 2))
    assert float(f(curve, 1.0)) > 0
    assert float(eqx.filter_jit(lambda k: k.stress.max())(instron)) == pytest.approx(77757.503)
    with pytest.raises(E.DataError, match="depth has 3 samples but force has 2"):
        dd.ForceDepthCurve([0, 1, 2], [0, 1])
    with pytest.raises(E.DataError, match="positive length"):
        dd.CompressionCurve([0, 0.1], [0, 1], diameter=-1.0)


# ================================================================ docs/data.md examples
def test_doc_examples(monkeypatch, tmp_path):
    monkeypatch.chdir(ROOT)
    assert_doctests_pass("data.md")
