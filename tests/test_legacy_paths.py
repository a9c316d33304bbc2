"""Runs trained before the package was split into folders keep loading."""

import yaml

from votesplat_ns.ns.datamanager import VoteDataManager, VoteDataManagerConfig
from votesplat_ns.ns.model import VoteSplatModel, VoteSplatModelConfig


def test_old_config_paths_resolve_to_the_moved_classes():
    # nerfstudio's config.yml pickles classes by their module path, as these lines do
    text = """
model_target: !!python/name:votesplat_ns.model.VoteSplatModel ''
model_config: !!python/name:votesplat_ns.model.VoteSplatModelConfig ''
dm_target: !!python/name:votesplat_ns.datamanager.VoteDataManager ''
dm_config: !!python/name:votesplat_ns.datamanager.VoteDataManagerConfig ''
"""
    loaded = yaml.load(text, Loader=yaml.Loader)
    assert loaded == {
        "model_target": VoteSplatModel,
        "model_config": VoteSplatModelConfig,
        "dm_target": VoteDataManager,
        "dm_config": VoteDataManagerConfig,
    }
