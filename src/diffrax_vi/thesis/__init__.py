"""The reproduction of Hirani (2000), Chapter 5: kept apart from the general studies,
which work on any scene and solver."""

from ._chapter5 import chapter5 as chapter5
