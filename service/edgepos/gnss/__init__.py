"""GNSS core: RINEX 3 readers, broadcast orbits, geodesy, atmospheric corrections and a WLS single-point solver.

Pure numpy/scipy, no web imports. Conventions used throughout the package:

- time: continuous GPS seconds since 1980-01-06 00:00:00 GPST (``gpst``); BeiDou times (BDT = GPST - 14 s)
  are converted on input and never leave a reader in their own scale;
- frames: WGS-84 ECEF (metres); local east-north-up (metres); geodetic latitude, longitude (radians) and
  ellipsoidal height (metres);
- units: metres, seconds, radians, dB-Hz.
"""
