"""Old import path of ``votesplat_ns.ns.model``: config.yml files of runs trained before the
package was split into folders name their classes here (nerfstudio pickles the class path)."""

from votesplat_ns.ns.model import *  # noqa: F401,F403
