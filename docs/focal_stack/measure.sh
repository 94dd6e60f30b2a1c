#!/bin/sh
# docs/focal_stack.md's measurement on aberrated-quarter.toml, from the repository root. Calibration goes to
# $BENCHCTL_CALIBRATION_DIR (default ./calibration), run folders to $RUNS (default runs/). Each step's wall time is
# printed after it ("== <seconds> s: <step>"). The focal stacks and CITL that need only the one-plane model run before
# the three-depth fit, so that an interrupted measurement still compares the ideal and the fitted model.
set -e
B=.venv/bin/benchctl
P=docs/focal_stack/aberrated-quarter.toml
D=docs/focal_stack
RUNS=${RUNS:-runs}
step() {                                                    # step <what> <procedure> <profile>
    start=$(date +%s)
    rc=0
    $B run "$D/$2" -p "$3" --out "$RUNS" || rc=$?
    echo "== $(( $(date +%s) - start )) s: $1 ($2), exit status $rc"
    return $rc
}
$B sim reset                                                # the stage at power-on: focused at the target plane
step "lookup tables" lut.toml $P
step "the twin's registration, the bench's first" registration.toml $D/ideal-quarter.toml
CAL=${BENCHCTL_CALIBRATION_DIR:-calibration}
mkdir -p "$CAL/aberrated-quarter" && cp "$CAL/ideal-quarter/registration.json" "$CAL/aberrated-quarter/"
step "the model from the target plane" model-calibration-target.toml $P
step "registration through the model" registration.toml $P
step "the model again, on that registration" model-calibration-target.toml $P
# The focus map (its dots through the model). On this bench red's dots did not sharpen where they were computed for
# (docs/focal_stack.md), and no map was stored: the stage's true map from its hidden [sim.focus] stands in for it.
step "the focus map" focus-calibration.toml $P || .venv/bin/python $D/true_focus_map.py
step "multi-plane SGD through the ideal model" stack-ideal.toml $P
step "... through the model fitted at the target plane" stack-fitted.toml $P
step "camera in the loop on the focal stack (the model fitted at the target plane)" citl.toml $P
step "the model from three focus depths" model-calibration.toml $P
step "... through the model fitted at three depths" stack-fitted.toml $P
