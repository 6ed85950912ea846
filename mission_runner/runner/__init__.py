"""Flying the algorithm on MAVLink vehicles: one vehicle's controller, its links, the mission clock,
the vehicle and ground processes, the operator's commands and the range aid."""
