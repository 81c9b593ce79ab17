"""A road map built from drives, and the NMPC's preview from it (docs/road.md).

* :mod:`~erva_ros.core.roadmap.profile` -- road profiles on a distance grid: the high-pass
  that removes what is not observable, profile matching (cross-correlation);
* :mod:`~erva_ros.core.roadmap.drive`   -- a recorded drive (what the ECU measured, the
  odometry) and its smoothed road estimate on the map grid;
* :mod:`~erva_ros.core.roadmap.store`   -- the map: inverse-variance fusion, incremental, many
  writers; in SQLite or on PostgreSQL (:mod:`~erva_ros.core.roadmap.location`,
  :mod:`~erva_ros.core.roadmap.backends`);
* :mod:`~erva_ros.core.roadmap.fleet`   -- a server map's local cache (route sections),
  migration between the databases, uploads of drives recorded offline;
* :mod:`~erva_ros.core.roadmap.bench`   -- ``erva map bench``: writers and fetches, timed;
* :mod:`~erva_ros.core.roadmap.preview` -- the preview from the map at the odometry position,
  corrected by matching the live road estimate with the map;
* :mod:`~erva_ros.core.roadmap.vehicle` -- the offline vehicle loop: ECU sensors, odometry,
  estimator, preview source, NMPC, plant;
* :mod:`~erva_ros.core.roadmap.bag_drive` -- drives from
  recorded HIL bags (decoded by erva_ros.core.contract);
* :mod:`~erva_ros.core.studies.map_study`   -- ``erva map-study``'s jobs.
"""

from erva_ros.core.errors import CLIError


class MapError(CLIError):
    """A map, a drive or an option cannot be used; the message is one line for the user."""


class MapUnreachable(MapError):
    """The map's server cannot be reached (a local cache of it may serve instead)."""


__all__ = ['MapError', 'MapUnreachable']
