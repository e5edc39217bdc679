"""hybridloc: crowd-sourced hybrid pedestrian dead reckoning + WiFi/RF SLAM for indoor positioning.

Conventions (written once, obeyed everywhere)
=============================================

Units
-----
* SI everywhere inside the library: metres, seconds, metres per second, m/s^2 for specific force,
  rad/s for angular rate, **tesla** for magnetic field (Android's microtesla are converted on read),
  hertz for radio frequency (Android's MHz are converted on read).
* Angles are **radians** internally. Degrees appear only at I/O boundaries and in printed reports,
  and a name that holds degrees says so (``heading_deg``). Conversion constants live in
  :mod:`hybridloc.units` (``DEG``, ``G0`` ...).
* Received signal strength is in dBm (``rssi_dbm``).
* Files written by hybridloc use the same SI units and radians unless a column name ends in a unit
  suffix such as ``_deg``.

Time
----
* One clock, float seconds (``t``). For a recording it is the recording's own clock: Indoor Location
  Competition traces use Unix time, so ``t = unix_ms / 1000``; PyShoe and OpenShoe files use their
  own ``ts`` or sample index / rate. Integer nanoseconds or tz-aware datetimes appear only at the
  database boundary.
* Time series are sorted and strictly increasing; readers report (and drop or reorder, as
  documented per reader) samples that are not.

Frames
------
* ``site`` / ``enu``: the local navigation frame of a site, East-North-Up, metres, with a per-site
  geodetic origin (:class:`hybridloc.geo.GeodeticOrigin`). Floor-plan coordinates of the Indoor
  Location Competition (x east, y north, metres) are this frame with z = 0 on each floor.
* ``nav``: the local-level frame of an inertial navigator; also ENU, z up, gravity along -z.
* ``body``: the sensor (IMU) axes of a phone or foot unit.
* Frames are written into names: ``pos_enu``, ``vel_enu``, ``accel_body``, ``gyro_body``,
  ``quat_wxyz`` (Hamilton, scalar first, rotating body vectors into nav: v_nav = q * v_body * q^-1),
  ``R_body_to_nav`` (3x3 rotation matrix with v_nav = R_body_to_nav @ v_body).
* **Heading** is the direction of travel in the site frame, measured counter-clockwise from East
  (the +x axis), in radians wrapped to (-pi, pi]. A step of length L and heading psi moves the walker
  by (L cos psi, L sin psi). Compass bearings (clockwise from North, as in NMEA HDT) are converted at
  I/O with :func:`hybridloc.units.heading_to_bearing_deg`.

Arrays
------
* Vectors are flat ``(n,)`` arrays; a block of N samples of a 3-vector is ``(N, 3)`` with time along
  axis 0. Covariances are ``(n, n)``; a series of them ``(N, n, n)``.
* Core types (:mod:`hybridloc.types`) are frozen dataclasses holding read-only numpy arrays.

Architecture
------------
* ``hybridloc`` (this package): algorithms, formats and the wire contract. Algorithms never touch
  the network or a database.
* ``hybridloc.server`` (``server/``) and ``hybridloc.clients`` (``clients/``) use the library and
  never import each other.
"""

__version__ = "0.1.0"
