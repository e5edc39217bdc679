"""Crowd SLAM: drift-corrected walks, loop closures and a crowd radio map, from walks with no survey.

A pure library (no network, no database; the server only loads and saves):

* :mod:`.walkgraph` - a walk's nodes (WiFi scans, sharp turns, survey marks, beacon passes, ends) and
  odometry with its white covariance; Indoor Location Competition files as walks;
* :mod:`.frontend` - fingerprint loop candidates between walks: freshness, similarity, an index,
  mutual top-k, a similarity -> distance model learned inside walks, PCM per walk pair;
* :mod:`.factors`, :mod:`.solve` - the factor graph (positions, per-segment scale and heading bias) and
  its robust solve (GNC-IRLS on sparse normal equations; GTSAM as the alternative), marginals;
* :mod:`.floorplan`, :mod:`.anchoring` - the walkable-area distance field and the placement of a group
  of walks on the plan;
* :mod:`.register` - placing one walk on a radio map by the consensus of its scans' fixes;
* :mod:`.pipeline` - all of it per floor, with EM against the crowd radio map;
* :mod:`.online` - one site live: walks added one by one (a solve of one walk against the held
  others), floors re-solved in batch, corrected tracks, quarantine, labels and crowd maps;
* :mod:`.output` - tracks.csv / tracks.geojson / loops.csv / crowd maps, and the plot;
* :mod:`.evaluate` - ``hybridloc eval slam``.
"""
