"""Ready systems for studies: a Lagrangian, a default state and what it conserves."""

from ._kepler import kepler as kepler, KeplerLagrangian as KeplerLagrangian
from ._scene import Scene as Scene


SCENES = {"kepler": kepler}
