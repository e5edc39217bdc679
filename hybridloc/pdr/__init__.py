"""Pedestrian dead reckoning: smartphone step-and-heading (:mod:`.phone`), dead reckoning of steps (:mod:`.deadreckoning`)."""

from .deadreckoning import DeadReckoning
from .phone import PhonePdr, PhonePdrConfig, dead_reckon, run_phone_pdr
from .steplength import BounceHeightLength, ConstantLength, FrequencyLength, KimLength, LengthCalibrator, WeinbergLength, make_model

__all__ = [
    "DeadReckoning",
    "PhonePdr",
    "PhonePdrConfig",
    "dead_reckon",
    "run_phone_pdr",
    "ConstantLength",
    "FrequencyLength",
    "KimLength",
    "BounceHeightLength",
    "WeinbergLength",
    "LengthCalibrator",
    "make_model",
]
