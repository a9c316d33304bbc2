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
        "external methods listed cheaply",
    }


def test_external_methods_are_listed_without_a_prompt_and_offered_from_the_command_line(monkeypatch):
    from nerfstudio.configs import external_methods
    from nerfstudio.utils.rich_utils import CONSOLE

    patches.apply()
    dummy = external_methods.ExternalMethodDummyTrainerConfig
    assert getattr(dummy.__post_init__, "_votesplat_cheap", False)
    patches.install_cheap_external_methods()  # idempotent: no second wrapper
    assert not getattr(dummy.__post_init__.__wrapped__, "_votesplat_cheap", False)

    shown = []
    monkeypatch.setattr(CONSOLE, "print", lambda *args, **kwargs: shown.append(args))
    configs, descriptions = external_methods.get_external_methods()  # listing them offers nothing
    assert shown == [] and set(configs) == set(descriptions) and "in2n" in configs

    method = external_methods.ExternalMethod("install me", [("x", "y")], pip_package=None)
    with pytest.raises(SystemExit) as stopped:  # as tyro makes it for `ns-train <method>`: nerfstudio's own offer
        dummy(method_name="x", method=method)
    assert stopped.value.code == 0 and shown == [("install me",)]


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


def test_splatfacto_get_viewmat_runs_without_the_viewers_interrupt_trace():
    import threading

    import torch
    from nerfstudio.models import splatfacto

    patches.install_untraced_viewmat()
    viewmat = splatfacto.get_viewmat
    patches.install_untraced_viewmat()  # idempotent: no second wrapper
    assert splatfacto.get_viewmat is viewmat and getattr(viewmat, "votesplat_untraced", False)
    assert not getattr(viewmat.__wrapped__, "votesplat_untraced", False)

    # a trace like the viewer's, raising on a line of the compiled function (the camera moved while dynamo traced it)
    class Moved(Exception):
        pass

    seen_inside = []

    def compiled(x):
        seen_inside.append(sys.gettrace())
        return x

    def interrupt(frame, event, arg):
        if event == "line" and frame.f_code is compiled.__code__:
            raise Moved
        return interrupt

    def render(function):  # in its own thread, as the viewer's renders run
        outcome = {}

        def run():
            sys.settrace(interrupt)
            try:
                outcome["value"] = function(3)
                outcome["trace_after"] = sys.gettrace()
            except Moved:
                outcome["moved"] = True
            finally:
                sys.settrace(None)

        thread = threading.Thread(target=run)
        thread.start()
        thread.join()
        return outcome

    assert render(compiled) == {"moved": True}
    assert render(patches.untraced(compiled)) == {"value": 3, "trace_after": interrupt} and seen_inside == [None]
    # splatfacto's own function still gives its view matrix through the wrapper
    c2w = torch.eye(4)[None, :3, :]
    assert torch.equal(splatfacto.get_viewmat(c2w), viewmat.__wrapped__(c2w))
