#!/bin/sh
# docs/focal_stack.md's measurement on aberrated-quarter.toml, from the repository root. Calibration goes to
# $BENCHCTL_CALIBRATION_DIR (default ./calibration), run folders to $RUNS (default runs/). Each step's wall time is
# printed after it ("== <seconds> s: <step>").
set -e
B=.venv/bin/benchctl
P=docs/focal_stack/aberrated-quarter.toml
D=docs/focal_stack
CAL=${BENCHCTL_CALIBRATION_DIR:-calibration}
RUNS=${RUNS:-runs}
step() {                                                    # step <what> <procedure> <profile>
    start=$(date +%s)
    $B run "$D/$2" -p "$3" --out "$RUNS"
    echo "== $(( $(date +%s) - start )) s: $1 ($2)"
}
$B sim reset                                                # the stage at power-on: focused at the target plane
step "lookup tables" lut.toml $P
step "the twin's registration, the bench's first" registration.toml $D/ideal-quarter.toml
mkdir -p "$CAL/aberrated-quarter" && cp "$CAL/ideal-quarter/registration.json" "$CAL/aberrated-quarter/"
step "the model from the target plane" model-calibration-target.toml $P
step "registration through the model" registration.toml $P
step "the model again, on that registration" model-calibration-target.toml $P
cp "$CAL/aberrated-quarter/optical-model.json" "$CAL/optical-model-one-plane.json"
step "the focus map (its dots through the model)" focus-calibration.toml $P
step "the model from three focus depths" model-calibration.toml $P
cp "$CAL/aberrated-quarter/optical-model.json" "$CAL/optical-model-three-planes.json"
step "multi-plane SGD through the ideal model" stack-ideal.toml $P
step "... through the model fitted at three depths" stack-fitted.toml $P
cp "$CAL/optical-model-one-plane.json" "$CAL/aberrated-quarter/optical-model.json"
step "... through the model fitted at the target plane" stack-fitted.toml $P
cp "$CAL/optical-model-three-planes.json" "$CAL/aberrated-quarter/optical-model.json"
step "camera in the loop on the focal stack" citl.toml $P
