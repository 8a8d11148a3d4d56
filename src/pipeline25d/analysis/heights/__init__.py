"""Building heights measured on the maps: how far each roof moved between the nadir and an oblique map.

On a north-up oblique map a point h metres above the DTM appears at its ground position
+ h·cot φ·d, d = (sin θ, cos θ) (see :mod:`pipeline25d.geometry.camera`); the nadir map shows it at
its ground position. A flat roof H metres high is therefore the nadir map's appearance of the
footprint, moved by H·cot φ along d. For each footprint and oblique map this module searches
that move u (metres along d, 0 ≤ u ≤ max_height·cot φ) and turns it into H = u / cot φ.

Matching (one footprint, one oblique map), all in nadir-grid pixels. Untextured models give
roofs of one uniform colour (often the same for every building), so a roof-only correlation is
degenerate; what pins a roof is where its colour *ends*:

* template: the nadir map's colours of the pixels whose centres lie inside the footprint;
  ring: pixels 2..ring_px+1 px outside it whose nadir colour differs from the nearest roof
  pixel's, which must *not* show that roof colour on the oblique map ("the roof ends where the
  footprint ends": no sliding inside a larger roof or onto the roof's own near-side wall); a
  ring pixel without data says nothing (left out of that move's score: beyond a model's edge
  a true roof borders no data, and beyond the map's a false one would);
* coarse scan at every pixel step of u: g(u) = 1 − mean truncated-quadratic colour loss
  (tolerance ``tol``; a pixel without data counts as a miss);
* peaks: a peak whose walls would hide ground that the oblique map shows unchanged from the
  nadir map in more than ``max_unchanged`` of the places tested is dropped; rival peaks (within
  ``max_second`` of the best, above the scan's median) are checked against that ground too:
  walls of a roof moved by u cover the area swept between footprint and roof, so a rival that
  sees clearly more of that area unchanged from the nadir map (``unchanged_margin``;
  roof-coloured places say nothing) is dropped. The best peak must
  match ≥ ``min_match`` of the template (else "hidden"), have no rival left ("ambiguous") and
  g must drop on both sides by ≥ ``min_drop`` × the share that a 2-px move uncovers ("flat":
  the roof could slide, e.g. along a row of same-coloured roofs);
* sub-pixel: (1) colour SSD over the template pixels matching near the peak (occluders and
  3 px around them left out), cubic splines, 0.1-px grid of u and a parabola; (2) around that,
  the anti-aliased edge pixels are compared through their nadir roof fraction a against
  a·(oblique colour 1.5 px inside) + (1 − a)·(oblique colour 1.5 px outside), so the roof's
  neighbour may differ between the maps (ground on the nadir map, the wall or another roof on
  the oblique map) without biasing u.

Per building: an ambiguous view is settled by the other views when exactly one of its rivals
agrees (``agree_m``) with their height; with three or more accepted views, a view more than
``outlier_m`` from the median of the others is rejected ("inconsistent": its roof was hidden
and a like roof further along the view matched), and two views that far apart are both
rejected (no majority says which matched); the accepted views are combined by their median and
``n_agree`` counts those within ``agree_m`` of it. Heights are relative to the ground that the
maps used (the DTM under the roof's outline).

Where the colours give no height (walls tinted like the roof, a roof sheared by the slope under
it), ``silhouette`` measures where the building's silhouette ends instead (see that module): the
roof above the mean ground under the footprint.

Modules: ``results`` (settings, per-view and per-building records, CSV), ``template``
(the nadir map's roof and its ring), ``matcher`` (one footprint on one oblique map),
``silhouette`` (where the building ends, every view), ``views``
(every footprint on every view, views combined), ``reference`` (model heights to compare
with, error statistics), ``cli`` (``pipeline25d heights``).
"""
