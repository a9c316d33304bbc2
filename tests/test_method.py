"""The votesplat method is found through nerfstudio's plugin registry and is well formed."""

from nerfstudio.plugins.registry import discover_methods

from votesplat_ns.model import VOTE_PARAM_NAMES, VoteSplatModelConfig


def test_votesplat_is_discovered_through_the_entry_point():
    methods, descriptions = discover_methods()
    assert "votesplat" in methods
    config = methods["votesplat"]
    assert config.method_name == "votesplat"
    assert isinstance(config.pipeline.model, VoteSplatModelConfig)
    assert "VoteSplat" in descriptions["votesplat"]


def test_every_gaussian_parameter_group_has_an_optimizer():
    # splatfacto's strategy densifies/prunes a gauss_params entry only if it has an optimizer.
    config = discover_methods()[0]["votesplat"]
    for name in ("means", "scales", "quats", "features_dc", "features_rest", "opacities", *VOTE_PARAM_NAMES):
        assert name in config.optimizers, name
