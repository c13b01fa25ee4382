"""Rerun logging for every rollout of the project, behind one small interface.

Why a single package: the plant, the characterization app and the training code all
produce the same kind of data (time, vehicle state, driver inputs, pose). Logging them
in one place keeps entity paths, units, colors and the viewer layout identical across
recordings, so two ``.rrd`` files can be opened side by side and compared.

Entity layout of a rollout called ``name`` (all series on the ``sim_time`` duration
timeline, in seconds)::

    {name}/state/<state_name>             scalar per sample (SI units): the actual state
    {name}/state/<state_name>/reference   its reference, when the rollout tracks one
    {name}/state/<state_name>/<overlay>   a series drawn on the state's plot (a prediction)
    {name}/error/<state_name>             actual - reference, when the rollout tracks one
    {name}/input/<input_name>             scalar per sample (deg, pedal fraction / -MPa)
    {name}/extra/<key>                    scalar(s) per sample
    {name}/car                            moved by a Transform3D column (the pose)
    {name}/car/body                       static Boxes3D: body and cabin
    {name}/car/wheel_<fl|fr|rl|rr>        static Cylinders3D; the front pair steers
    {name}/path                           static LineStrips3D of the whole trajectory

Every plotted line has a name (``SeriesLines``): a state's plot reads ``reference``,
``actual`` and the overlays' keys; the error plot ``<state> error``.

:class:`Recorder` is the null recorder (selected with ``recorder=none``);
:class:`RerunRecorder` writes a ``.rrd`` file. Both are built the same way from Hydra
(``_partial_: true``) and then called with ``path=...``; ``conf/recorder/rerun.yaml``
gives the plant's steering ratio, so the drawn front wheels turn by the road-wheel angle.

The parts: ``base`` (the interface, the null recorder), ``rerun_file`` (the ``.rrd`` writer),
``layout`` (the viewer's default blueprint), ``car`` (the 3D car), ``entities`` (paths, times,
colors, shape checks). Imports nothing of the project.
"""

from harness.recorder.base import Recorder
from harness.recorder.car import (
    CAR_HEIGHT_M,
    CAR_LENGTH_M,
    CAR_WIDTH_M,
    FRONT_AXLE_X_M,
    REAR_AXLE_X_M,
    WHEEL_RADIUS_M,
)
from harness.recorder.entities import SIM_TIMELINE
from harness.recorder.layout import MAX_VIEWS, MIN_STATE_SPAN
from harness.recorder.rerun_file import RerunRecorder

__all__ = [
    "CAR_HEIGHT_M",
    "CAR_LENGTH_M",
    "CAR_WIDTH_M",
    "FRONT_AXLE_X_M",
    "MAX_VIEWS",
    "MIN_STATE_SPAN",
    "REAR_AXLE_X_M",
    "SIM_TIMELINE",
    "WHEEL_RADIUS_M",
    "Recorder",
    "RerunRecorder",
]
