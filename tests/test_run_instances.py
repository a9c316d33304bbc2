"""One set of instances per trained run (ns/run_instances.py): computed once, kept beside the run,
rebuilt when the checkpoint, the settings or the code change, never read half-written."""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import time

import numpy as np
import pytest

from votesplat_ns.core.clustering import ClusteringOptions
from votesplat_ns.core.instances import InstanceSet
from votesplat_ns.core.ply_io import LEFTOVER_AGE_S
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.ns import run_instances as record
from votesplat_ns.ns.run_instances import RECORD_FOLDER, InstanceSettings, run_instances

# no training masks in these tests: the vote clustering alone (the mask check has its own tests)
UNCHECKED = InstanceSettings.make(mask_check=False)


def blob_scene(seed: int = 0, per_blob: int = 150) -> TrainedScene:
    """Three blobs of Gaussians whose votes point at their blob's centre, on one level."""
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    truth = np.repeat(np.arange(3), per_blob)
    means = centres[truth] + rng.normal(0, 0.3, (truth.size, 3))
    votes = centres[truth] + rng.normal(0, 0.02, (truth.size, 3))
    n = truth.size
    return TrainedScene(
        means=means.astype(np.float32),
        log_scales=np.full((n, 3), -3.0, np.float32),
        quats=np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1)),
        opacity_logits=np.zeros(n, np.float32),
        sh_dc=np.zeros((n, 3), np.float32),
        sh_rest=None,
        vote_offsets=(votes - means).astype(np.float32)[:, None, :],
        vote_support=np.ones((n, 1), np.float32),
        level_names=("instance",),
        sh_degree=0,
    )


@pytest.fixture
def counted(monkeypatch):
    """Counts the clusterings run_instances makes."""
    calls = []
    original = record.cluster_levels

    def cluster_levels(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(record, "cluster_levels", cluster_levels)
    return calls


def test_computed_once_then_read_from_beside_the_run(tmp_path, counted):
    scene = blob_scene()
    first = run_instances(scene, tmp_path, UNCHECKED)
    assert first.level("instance").num_instances == 3 and len(counted) == 1
    assert (tmp_path / RECORD_FOLDER / "instances.json").is_file()
    messages = []
    second = run_instances(scene, tmp_path, UNCHECKED, log=messages.append)
    assert len(counted) == 1 and messages == []  # read, not computed
    np.testing.assert_array_equal(second.level("instance").ids, first.level("instance").ids)
    kept = json.loads((tmp_path / RECORD_FOLDER / "instances.json").read_text())["record"]
    assert set(kept["key"]) == set(record.KEY_PARTS) and kept["settings"]["mask_check"] is False


def test_another_checkpoint_is_computed_again_with_one_line(tmp_path, counted):
    scene = blob_scene()
    run_instances(scene, tmp_path, UNCHECKED)
    moved = dataclasses.replace(scene, means=scene.means + np.float32(0.01))
    messages = []
    run_instances(moved, tmp_path, UNCHECKED, log=messages.append)
    assert len(counted) == 2
    assert len(messages) == 1 and "computed for another checkpoint; computing them again" in messages[0]
    run_instances(moved, tmp_path, UNCHECKED, log=messages.append)
    assert len(counted) == 2 and len(messages) == 1  # the new record is the one kept


def test_other_settings_and_other_code_are_computed_again(tmp_path, counted, monkeypatch):
    scene = blob_scene()
    run_instances(scene, tmp_path, UNCHECKED)
    messages = []
    other = InstanceSettings.make(ClusteringOptions(min_cluster_size=20), mask_check=False)
    run_instances(scene, tmp_path, other, log=messages.append)
    assert len(counted) == 2 and "other clustering settings" in messages[-1]
    monkeypatch.setattr(record, "code_digest", lambda: "another")
    run_instances(scene, tmp_path, other, log=messages.append)
    assert len(counted) == 3 and "another version of the instance code" in messages[-1]


def test_the_key_ignores_what_does_not_change_the_instances(tmp_path):
    scene = blob_scene()
    same = dataclasses.replace(scene, sh_dc=scene.sh_dc + 1.0, device="cuda:0")  # colours and device
    settings = InstanceSettings.make(mask_check=True)
    assert record.record_key(scene, settings, None) == record.record_key(same, settings, None)
    # mask-check settings only matter while the check is on
    assert record.record_key(scene, UNCHECKED, None) == record.record_key(
        scene, InstanceSettings.make(mask_check=False, mask_check_views=3), None
    )


def test_a_read_only_run_folder_computes_in_memory_with_one_warning(tmp_path, counted, monkeypatch):
    def read_only(path, tag=""):  # what mkdir says in a read-only folder (root may write anywhere, so simulated)
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(record, "make_temp_dir", read_only)
    messages = []
    instances = run_instances(blob_scene(), tmp_path, UNCHECKED, log=messages.append)
    assert instances.level("instance").num_instances == 3
    assert messages == [
        f"Warning: cannot keep the instances in {tmp_path / RECORD_FOLDER} (Permission denied); they were computed "
        "in memory and will be computed again next time"
    ]
    assert list(tmp_path.iterdir()) == []


def test_a_folder_that_cannot_be_written_computes_in_memory_with_one_warning(tmp_path, counted):
    run_dir = tmp_path / "run"
    run_dir.write_text("a file where the run folder should be")  # every write below it fails, also as root
    messages = []
    instances = run_instances(blob_scene(), run_dir, UNCHECKED, log=messages.append)
    assert instances.level("instance").num_instances == 3
    assert len(messages) == 1 and messages[0].startswith("Warning: cannot keep the instances")


def test_an_interrupted_write_leaves_nothing_that_is_read(tmp_path, counted, monkeypatch):
    scene = blob_scene()

    def killed(self, folder, instance_extra=None, extra=None):
        (folder / "instance_ids.npz").write_bytes(b"half")
        raise KeyboardInterrupt  # Ctrl-C in the middle of the write

    monkeypatch.setattr(InstanceSet, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        run_instances(scene, tmp_path, UNCHECKED)
    assert list(tmp_path.iterdir()) == []  # neither a record nor its staging folder
    monkeypatch.undo()
    run_instances(scene, tmp_path, UNCHECKED)
    assert (tmp_path / RECORD_FOLDER).is_dir()


def test_leftovers_of_a_killed_write_are_swept_and_a_damaged_record_is_rebuilt(tmp_path, counted):
    scene = blob_scene()
    leftover = tmp_path / f".{RECORD_FOLDER}.partial.tmp-123-abc"  # what kill -9 mid-write leaves
    leftover.mkdir()
    (leftover / "instances.json").write_text("{")
    old = time.time() - 2 * LEFTOVER_AGE_S
    os.utime(leftover, (old, old))
    fresh = tmp_path / f".{RECORD_FOLDER}.partial.tmp-456-def"  # another process writing right now
    fresh.mkdir()
    run_instances(scene, tmp_path, UNCHECKED)
    assert not leftover.exists() and fresh.exists()
    (tmp_path / RECORD_FOLDER / "instances.json").write_text('{"record": ')  # damaged
    messages = []
    instances = run_instances(scene, tmp_path, UNCHECKED, log=messages.append)
    assert len(counted) == 2 and "unreadable record" in messages[0]
    assert instances.level("instance").num_instances == 3


def test_without_training_masks_the_check_is_skipped_and_nothing_is_kept(tmp_path, counted):
    messages = []
    instances = run_instances(blob_scene(), tmp_path, InstanceSettings.make(mask_check=True), log=messages.append)
    assert instances.level("instance").num_instances == 3
    assert len(messages) == 1 and "without the mask check" in messages[0]
    assert not (tmp_path / RECORD_FOLDER).exists()  # a later call with the masks must not read unchecked instances


def test_the_record_gets_the_users_umask(tmp_path):
    previous = os.umask(0o027)
    try:
        run_instances(blob_scene(), tmp_path, UNCHECKED)
    finally:
        os.umask(previous)
    folder = tmp_path / RECORD_FOLDER
    assert stat.S_IMODE(folder.stat().st_mode) == 0o750
    assert {stat.S_IMODE(p.stat().st_mode) for p in folder.iterdir()} == {0o640}


def test_export_query_click_and_viewer_show_one_set_of_instances(trained_demo, tmp_path):
    """On the demo run: the export, `votesplat query`/`click` and the ns-viewer panel give the same count and
    the same id for every Gaussian at every level, and a record made with other settings is rebuilt, not used."""
    from types import SimpleNamespace

    from votesplat_ns.ns.export import ExportVoteSplatInstances
    from votesplat_ns.ns.run import load_run
    from votesplat_ns.ns.selection import QueryScene
    from votesplat_ns.ns.viewer import scene_from_model

    run_dir = trained_demo.parent
    kept = run_dir / RECORD_FOLDER
    other = ExportVoteSplatInstances(load_config=trained_demo, output_dir=tmp_path / "other", num_views=0, seed=1)
    other.main()  # a record made with other settings: the commands below must not read it
    assert json.loads((kept / "instances.json").read_text())["record"]["settings"]["clustering"]["seed"] == 1

    ExportVoteSplatInstances(load_config=trained_demo, output_dir=tmp_path / "export", num_views=0).main()
    exported = InstanceSet.load(tmp_path / "export")
    assert json.loads((kept / "instances.json").read_text())["record"]["settings"]["clustering"]["seed"] == 0
    clicked = {name: QueryScene.from_config(trained_demo, level=name).level for name in exported.level_names}

    pipeline, _, _ = load_run(trained_demo)
    model = pipeline.model
    model.instance_gui_viewer_control.viewer = SimpleNamespace(
        pipeline=pipeline, log_filename=run_dir / "viewer_log_filename.txt"
    )
    viewer = model.viewer_state.state.instances_for(scene_from_model(model))

    for name in exported.level_names:
        ids = exported.level(name).ids
        assert exported.level(name).num_instances > 0
        for other_ids, where in ((clicked[name].ids, "query/click"), (viewer.level(name).ids, "viewer")):
            np.testing.assert_array_equal(other_ids, ids, err_msg=f"{where} at level {name!r}")
        assert clicked[name].num_instances == viewer.level(name).num_instances == exported.level(name).num_instances
