"""Provenance: one release version, a source hash that follows every edit, and caches keyed by it."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pytest
import torch

import benchctl
from benchctl import provenance
from benchctl.calibration.calibrated import Calibrated
from benchctl.holograms import cache as hologram_cache
from benchctl.optics.planes import DepthSweep, PlaneChoice
from benchctl.profiles import load_profile
from benchctl.targets import load_target, prepare_target


def test_release_version_is_pyprojects() -> None:
    pyproject = (Path(__file__).parents[1] / "pyproject.toml").read_text()
    assert f'version = "{benchctl.__version__}"' in pyproject
    assert benchctl.__version__ == importlib.metadata.version("benchctl")


def test_source_hash_follows_every_edit_and_rename(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    monkeypatch.setattr(provenance, "PACKAGE_DIR", tmp_path)

    def fresh() -> str:
        provenance.source_hash.cache_clear()
        return provenance.source_hash()

    first = fresh()
    assert len(first) == 16 and fresh() == first
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")
    edited = fresh()
    (tmp_path / "sub" / "b.py").rename(tmp_path / "sub" / "c.py")
    renamed = fresh()
    (tmp_path / "notes.txt").write_text("not code")
    assert len({first, edited, renamed}) == 3 and fresh() == renamed
    provenance.source_hash.cache_clear()


def test_code_identity_names_version_source_and_git_state() -> None:
    identity = provenance.code_identity()
    assert identity["version"] == benchctl.__version__
    assert identity["source_sha256"] == provenance.source_hash()
    if "git_commit" in identity:  # a checkout; an installed wheel has no git state
        assert len(str(identity["git_commit"])) == 40 and isinstance(identity["git_dirty"], bool)


def test_hologram_cache_misses_after_a_code_edit(small_profile_path: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BENCHCTL_CACHE_DIR", str(tmp_path / "cache"))
    profile = load_profile(small_profile_path)
    target = prepare_target(load_target("chart:siemens", (48, 80)), (64, 96), (48, 80))

    def green() -> hologram_cache.Hologram:
        return hologram_cache.hologram(Calibrated(profile), target, "green", "dpac", iterations=None, seed=0,
                                       checkpoint=None)

    assert not green().cached and green().cached
    monkeypatch.setattr(hologram_cache, "source_hash", lambda: "0123456789abcdef")  # as after editing a method
    again = green()
    assert not again.cached and green().cached
    assert len(list((tmp_path / "cache" / "holograms").glob("*.npz"))) == 2
    assert torch.equal(torch.as_tensor(again.gray), torch.as_tensor(green().gray))


def test_run_records_and_generate_metrics_carry_the_code_identity(small_profile_path: Path, tmp_path: Path) -> None:
    from benchctl.holograms.generate import run_generate
    from benchctl.runner.record import package_versions

    assert package_versions()["benchctl_code"] == provenance.code_identity()
    metrics = run_generate("chart:siemens", load_profile(small_profile_path), tmp_path / "out", method="dpac",
                           colours=["green"])
    assert metrics["benchctl_code"]["source_sha256"] == provenance.source_hash()


def test_refined_learned_methods_key_the_cache_by_their_networks_checkpoint(
        small_profile_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """"ccnn-dcm4+sgd" runs ccnn-dcm4's checkpoint, found by the one search rule (checkpoints/<profile>/ in the
    working folder): its bytes key the cache, so a retrained network is never served an old hologram."""
    monkeypatch.chdir(tmp_path)
    bench = Calibrated(load_profile(small_profile_path))
    shipped = tmp_path / "checkpoints" / bench.profile.name / "ccnn-dcm4.pt"
    shipped.parent.mkdir(parents=True)
    target = prepare_target(load_target("chart:siemens", (48, 80)), (64, 96), (48, 80))
    entries = []
    for weights in (b"first weights", b"retrained weights"):
        shipped.write_bytes(weights)
        entries.append(hologram_cache.cache_entry(bench, target, "green", "ccnn-dcm4+sgd", iterations=5, seed=0,
                                                  checkpoint=None))
    (first, used), (second, _) = entries
    assert Path(used).resolve() == shipped.resolve() and first != second
    assert hologram_cache.cache_entry(bench, target, "green", "sgd", iterations=5, seed=0, checkpoint=None)[1] is None


def test_a_scene_with_depth_keys_the_cache_by_its_planes_and_their_sweep(small_profile_path: Path) -> None:
    """The same scene at the same planes, once held fixed and once swept (`--planes auto` on continuous depth), are two
    holograms: neither is served for the other."""
    bench = Calibrated(load_profile(small_profile_path))
    target = prepare_target(load_target("chart:siemens", (48, 80)), (64, 96), (48, 80))
    depth = torch.linspace(0.016, 0.024, 96, dtype=torch.float64).repeat(64, 1)
    fixed = PlaneChoice((0.018, 0.022), "fixed")
    swept = PlaneChoice((0.018, 0.022), "swept", DepthSweep(((0.017, 0.018, 0.019), (0.021, 0.022, 0.023)), 0.0005))
    moved = PlaneChoice((0.018, 0.0225), "fixed")
    keys = [hologram_cache.cache_entry(bench, target, "green", "sgd", iterations=5, seed=0, checkpoint=None,
                                       depth_m=depth, planes=choice)[0] for choice in (fixed, swept, moved, fixed)]
    assert len(set(keys[:3])) == 3 and keys[3] == keys[0]
    with pytest.raises(ValueError, match="needs the planes it is shown at"):
        hologram_cache.cache_entry(bench, target, "green", "sgd", iterations=5, seed=0, checkpoint=None, depth_m=depth)
