"""Measuring the method, not running it: nothing in the training or export path imports this folder.

The instance scorer (evaluation), the LERF-OVS protocol (lerf_ovs), a SAM-like mask noise model
(mask_noise) and the mitsuba scene generator with exact ground truth (synthetic/, ``votesplat synth``).
"""
