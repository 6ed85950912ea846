"""Moving-target enclosing missions for multi-drone swarms.

The package is layered: ``enclosing`` is the paper's algorithm (numpy only), ``sim`` the numeric
simulator around it, ``bus`` the vehicle-to-vehicle message exchange, and the runner that flies the
algorithm on MAVLink vehicles. ``config`` is the one typed scenario model all of them read.
"""

__version__ = "0.1.0"
