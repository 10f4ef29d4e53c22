"""`difftissue export --specimen FILE`: a tet mesh from a file as the specimen (docs/cli.md,
docs/export.md): the same deck as the generated block when the file holds that block, its
length unit required, a file whose base or top is no flat face refused, and the XPBD load-set
calibration built on the file's mesh."""

from __future__ import annotations

import numpy as np
import pytest

from difftissue.cli import main
from difftissue.errors import ConfigError
from difftissue.export import MaterialCard, write_card
from difftissue.mesh import TetMesh, block, write_mesh


@pytest.fixture()
def files(tmp_path):
    card = MaterialCard(model="fem_neo_hookean", parameters={"youngs_modulus": {"value": 1e4, "unit": "Pa"},
                                                             "poisson_ratio": {"value": 0.45, "unit": "1"}}, name="skin")
    write_card(card, tmp_path / "card.json", force=True)
    mesh = block((0.01, 0.01, 0.005), (4, 4, 2))
    write_mesh(tmp_path / "block_mm.vtu", TetMesh(np.asarray(mesh.points) * 1e3, mesh.tets), overwrite=True)
    return tmp_path, mesh


def _export(tmp_path, out, *extra):
    return main(["export", str(tmp_path / "card.json"), "--out", str(tmp_path / out), "--force", *extra])


@pytest.mark.parametrize("target", ["febio", "abaqus"])
def test_a_block_from_a_file_gives_the_generated_blocks_deck(files, target):
    tmp_path, _ = files
    suffix = {"febio": "feb", "abaqus": "inp"}[target]
    assert _export(tmp_path, f"gen.{suffix}", "--to", target, "--specimen", "block:10,10,5:4,4,2") == 0
    assert _export(tmp_path, f"file.{suffix}", "--to", target, "--specimen", str(tmp_path / "block_mm.vtu"), "--unit", "mm") == 0

    def body(name):  # the decks without their creation time
        return [ln for ln in (tmp_path / name).read_text().splitlines() if "created" not in ln]

    assert body(f"file.{suffix}") == body(f"gen.{suffix}")


def test_a_mesh_file_needs_its_unit_exists_and_has_flat_faces(files, capsys):
    tmp_path, mesh = files
    assert _export(tmp_path, "x.feb", "--to", "febio", "--specimen", str(tmp_path / "block_mm.vtu")) == 2
    assert "a mesh file needs --unit, the length unit of its coordinates" in capsys.readouterr().err
    assert _export(tmp_path, "x.feb", "--to", "febio", "--specimen", str(tmp_path / "none.vtu"), "--unit", "mm") == 2
    assert "expected block:LX,LY,LZ:NX,NY,NZ, indentation, fitted or a mesh file (no such file)" in capsys.readouterr().err
    p = np.asarray(mesh.points) * 1e3
    top = np.flatnonzero(p[:, 2] == p[:, 2].max())
    p[top[len(top) // 2], 2] += 1.0  # one top node raised: the highest "face" is a single vertex
    write_mesh(tmp_path / "peak.vtu", TetMesh(p, mesh.tets), overwrite=True)
    assert _export(tmp_path, "x.feb", "--to", "febio", "--specimen", str(tmp_path / "peak.vtu"), "--unit", "mm") == 1
    err = capsys.readouterr().err
    assert "no flat top face normal to z" in err and "1 node(s)" in err
    assert not (tmp_path / "x.feb").exists()


def test_an_unstructured_mesh_file_is_a_specimen(files):
    """Interior nodes moved (no longer the generator's lattice): exported with the file's own
    nodes, base and top found as the flat faces at the smallest and largest z."""
    tmp_path, mesh = files
    p = np.asarray(mesh.points) * 1e3
    inner = (p[:, 0] > 0) & (p[:, 0] < 10) & (p[:, 1] > 0) & (p[:, 1] < 10) & (p[:, 2] > 0) & (p[:, 2] < 5)
    p[inner] += np.random.default_rng(0).uniform(-0.4, 0.4, (int(inner.sum()), 3))
    write_mesh(tmp_path / "moved.vtu", TetMesh(p, mesh.tets), overwrite=True)
    assert _export(tmp_path, "m.inp", "--to", "abaqus", "--specimen", str(tmp_path / "moved.vtu"), "--unit", "mm") == 0
    text = (tmp_path / "m.inp").read_text()
    moved = p[np.flatnonzero(inner)[0]] * 1e-3
    assert any(np.allclose([float(v) for v in ln.split(",")[1:4]], moved, rtol=0, atol=1e-12)
               for ln in text.splitlines() if ln[:1].strip().isdigit() and ln.count(",") == 3)


def test_load_set_is_calibrated_on_the_files_mesh(files, monkeypatch, capsys):
    """`--to xpbd --specimen FILE --load-set`: the loads are built on the file's mesh (in metres);
    the calibration is intercepted after its arguments are checked (no solve)."""
    import difftissue.budget

    tmp_path, mesh = files
    seen = []

    def intercepted(mesh_, model_kind, material, loads, settings, **kw):
        np.testing.assert_allclose(np.asarray(mesh_.points), np.asarray(mesh.points), rtol=0, atol=1e-15)
        np.testing.assert_array_equal(np.asarray(mesh_.tets), np.asarray(mesh.tets))
        seen.append([(ld.shape, ld.depth) for ld in loads])
        raise ConfigError("intercepted after the arguments were checked")

    monkeypatch.setattr(difftissue.budget, "calibrate_for_load_set", intercepted)
    (tmp_path / "loads.toml").write_text('[budget]\nlength_unit = "mm"\n\n[[budget.loads]]\nshape = "platen"\ndepth = 0.1\n')
    rc = _export(tmp_path, "x.json", "--to", "xpbd", "--dt", "2.5e-4", "--iterations", "10", "--load-set", str(tmp_path / "loads.toml"),
                 "--specimen", str(tmp_path / "block_mm.vtu"), "--unit", "mm")
    assert rc == 1 and "intercepted after the arguments were checked" in capsys.readouterr().err
    assert seen == [[("platen", pytest.approx(1e-4, rel=1e-12))]]
