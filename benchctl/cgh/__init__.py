"""Hologram generation: the method interface and registry, the optical setup, the classical methods.

Methods register themselves when their module is imported; importing this package registers DPAC ("dpac"),
Gerchberg-Saxton ("gs") and SGD ("sgd"). Imports only `benchctl.optics` from the rest of benchctl.
"""

from benchctl.cgh.dpac import DPAC, double_phase
from benchctl.cgh.gerchberg_saxton import GERCHBERG_SAXTON
from benchctl.cgh.method import (
    METHODS,
    Algorithm,
    Method,
    Progress,
    check_target,
    get_method,
    method_names,
    register,
    stopped_improving,
    wrap_phase,
)
from benchctl.cgh.sgd import SGD, roi_loss, sgd_method
from benchctl.optics.setup import OpticalSetup

__all__ = [
    "DPAC",
    "GERCHBERG_SAXTON",
    "METHODS",
    "SGD",
    "Algorithm",
    "Method",
    "OpticalSetup",
    "Progress",
    "check_target",
    "double_phase",
    "get_method",
    "method_names",
    "register",
    "roi_loss",
    "sgd_method",
    "stopped_improving",
    "wrap_phase",
]
