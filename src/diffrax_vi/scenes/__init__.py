"""Ready systems for studies: a Lagrangian, a default state, what it conserves and,
where known, its exact solution."""

from ._chaotic import (
    double_pendulum as double_pendulum,
    DoublePendulumLagrangian as DoublePendulumLagrangian,
    henon_heiles as henon_heiles,
    HenonHeilesLagrangian as HenonHeilesLagrangian,
)
from ._fpu import fpu as fpu, FPULagrangian as FPULagrangian
from ._kepler import kepler as kepler, KeplerLagrangian as KeplerLagrangian
from ._learned import (
    fit_potential as fit_potential,
    learned as learned,
    LearnedLagrangian as LearnedLagrangian,
)
from ._mechanisms import (
    cartesian_pendulum as cartesian_pendulum,
    CartesianPendulumLagrangian as CartesianPendulumLagrangian,
    Circle as Circle,
    ControlTorque as ControlTorque,
    DampedDrive as DampedDrive,
    forced_duffing as forced_duffing,
    four_bar as four_bar,
    FourBarLagrangian as FourBarLagrangian,
    LoopClosure as LoopClosure,
    swing_up as swing_up,
)
from ._multibody import (
    rigid_chain as rigid_chain,
    rigid_double_pendulum as rigid_double_pendulum,
    RigidBodiesLagrangian as RigidBodiesLagrangian,
)
from ._one_dof import (
    duffing as duffing,
    DuffingLagrangian as DuffingLagrangian,
    falling_particle as falling_particle,
    FallingParticleLagrangian as FallingParticleLagrangian,
    oscillator as oscillator,
    OscillatorLagrangian as OscillatorLagrangian,
    pendulum as pendulum,
    PendulumLagrangian as PendulumLagrangian,
)
from ._rigid import (
    free_rigid_body as free_rigid_body,
    FreeRigidBodyLagrangian as FreeRigidBodyLagrangian,
    heavy_top as heavy_top,
    pendulum_3d as pendulum_3d,
    RigidBodyLagrangian as RigidBodyLagrangian,
    satellite as satellite,
    SatelliteLagrangian as SatelliteLagrangian,
)
from ._scene import Scene as Scene
from ._solar import (
    NBodyLagrangian as NBodyLagrangian,
    outer_solar_system as outer_solar_system,
)
from ._three_body import pythagorean_three_body as pythagorean_three_body
from ._wire import bead_wire as bead_wire, BeadWireLagrangian as BeadWireLagrangian


SCENES = {
    "kepler": kepler,
    "falling_particle": falling_particle,
    "oscillator": oscillator,
    "duffing": duffing,
    "pendulum": pendulum,
    "double_pendulum": double_pendulum,
    "henon_heiles": henon_heiles,
    "fpu": fpu,
    "outer_solar_system": outer_solar_system,
    "pythagorean_three_body": pythagorean_three_body,
    "learned": learned,
    "bead_wire": bead_wire,
    "forced_duffing": forced_duffing,
    "cartesian_pendulum": cartesian_pendulum,
    "four_bar": four_bar,
    "free_rigid_body": free_rigid_body,
    "heavy_top": heavy_top,
    "pendulum_3d": pendulum_3d,
    "satellite": satellite,
    "rigid_double_pendulum": rigid_double_pendulum,
    "rigid_chain": rigid_chain,
}
"""Every scene by name (the names `diffrax-vi --scene` accepts), each with the
function that makes it: called with no arguments, it gives the scene at its default
parameters."""

MONITORED = ("kepler", "outer_solar_system", "pythagorean_three_body")
"""The names of the scenes with a step-size monitor (`Scene.monitor`), which the
study's `+Adaptive` methods step by."""
