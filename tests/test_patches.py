"""The plugin's patches of upstream code are applied from one place (votesplat_ns/ns/patches.py)."""

import sys
import warnings

import pytest

from votesplat_ns.ns import patches


def test_apply_installs_every_process_wide_patch_once():
    patches.apply()
    hook = sys.excepthook
    finders = [f for f in sys.meta_path if isinstance(f, patches._ExporterFinder)]
    patches.apply()  # idempotent: no second wrapper, no second finder
    assert sys.excepthook is hook and getattr(hook, "_votesplat_input_errors", False)
    assert len([f for f in sys.meta_path if isinstance(f, patches._ExporterFinder)]) == len(finders) == 1
    assert {p.name for p in patches.PATCHES} == {
        "checkpoint safe globals",
        "one-line input errors",
        "ns-export votesplat-instances",
        "checkpoint checked first",
    }


def test_versions_other_than_the_patched_ones_warn_once(monkeypatch):
    monkeypatch.setattr(patches.metadata, "version", lambda name: "9.9.9")
    monkeypatch.setattr(patches, "_version_warned", False)
    with pytest.warns(
        RuntimeWarning, match=r"nerfstudio 9\.9\.9 \(written for 1\.1\.5\), gsplat 9\.9\.9 \(written for 1\.4\.0\)"
    ):
        patches.apply()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        patches.apply()  # said once per process
    assert patches.version_mismatches() == {"nerfstudio": ("9.9.9", "1.1.5"), "gsplat": ("9.9.9", "1.4.0")}


def test_a_failing_patch_warns_and_the_others_still_apply(monkeypatch):
    applied = []

    def broken():
        raise ImportError("exporter moved")

    monkeypatch.setattr(
        patches,
        "PATCHES",
        (patches.Patch("broken", "somewhere", broken), patches.Patch("fine", "elsewhere", lambda: applied.append(1))),
    )
    with pytest.warns(RuntimeWarning, match=r"patch 'broken' \(somewhere\) not applied: exporter moved"):
        patches.apply()
    assert applied == [1]
