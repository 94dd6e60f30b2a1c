"""Hologram generation: the method interface and registry, the optical setup, the classical methods.

Methods register themselves when their module is imported; importing this package registers every method
there is: DPAC ("dpac"), Gerchberg-Saxton ("gs"), SGD ("sgd") and the learned networks with their SGD
refinements (`benchctl.cgh.learned`). Imports only `benchctl.optics` from the rest of benchctl.
"""

from benchctl.cgh import learned  # registers the learned methods: last, as it builds on the above
from benchctl.cgh.dpac import DPAC, double_phase
from benchctl.cgh.gerchberg_saxton import GERCHBERG_SAXTON
from benchctl.cgh.method import (
    DEFAULT_METHOD,
    METHODS,
    REFINED_SUFFIX,
    Algorithm,
    Method,
    Networks,
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
    "DEFAULT_METHOD",
    "DPAC",
    "GERCHBERG_SAXTON",
    "METHODS",
    "REFINED_SUFFIX",
    "SGD",
    "Algorithm",
    "Method",
    "Networks",
    "OpticalSetup",
    "Progress",
    "check_target",
    "double_phase",
    "get_method",
    "learned",
    "method_names",
    "register",
    "roi_loss",
    "sgd_method",
    "stopped_improving",
    "wrap_phase",
]
