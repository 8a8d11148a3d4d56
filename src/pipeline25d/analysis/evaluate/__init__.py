"""Independent check of orthorectification: ground offsets of an oblique map against the nadir map.

The nadir map (az000_el90) is exact for ground by construction, so wherever ground is visible
in both, an oblique map's ground should sit on the same map coordinates. This module measures
by how much it does not, by image correlation on square windows of ground; it uses neither the
pipeline's GCPs nor its warp scores.

Which pixels count. A pixel of a window is usable when it is fully opaque (alpha 255) in both
maps and, given a surface and a terrain model (DSM, DTM), it is ground that the oblique view
sees: DSM − DTM below ``max_height``, and not hidden behind anything standing on the ground
along the line of sight toward that view's camera (see :func:`hidden_by_relief`; heights above
the terrain for the pipeline's terrain-relative maps, where terrain never hides terrain,
absolute heights for maps projected onto a plane); everything else, grown by ``dilate_m``, is
masked out. A window is measured when at least ``min_ground_fraction`` of its pixels are usable
and they have texture, so dense cities with narrow streets, trees and holes in the mesh still
yield windows. Without a DSM and DTM only opacity masks pixels.

How a window is measured (no bias toward zero from the mask): the integer shift is the peak of
the masked normalised cross-correlation (Padfield 2012: only usable pixels of both maps enter,
at every trial shift), then a Gauss–Newton (Lucas–Kanade) least-squares fit of the shift, a
gain and an offset on the usable pixels alone refines it to sub-pixel, interpolating the
oblique map with quintic B-splines, until the update is below 1e-3 px. Masked pixels are never
zero-filled and correlated, so identical mask edges in both maps cannot pull the result
toward zero. A window fails (counted with its reason, never dropped) when the fit's normal
matrix is ill-conditioned (texture in one direction only: the aperture problem), the
correlation surface has a second peak nearly as high as the first, the fit does not converge,
the aligned NCC is below ``min_ncc`` or the shift exceeds ``max_shift_px``.

Sign convention: an offset (dx_px, dy_px) says where the oblique map shows the ground relative
to where the nadir map shows it, in map pixels, x east and y NORTH. A ground feature that the
nadir map shows at map coordinates (X, Y) appears in the oblique map at
(X + dx_px·gsd, Y + dy_px·gsd). (Rows grow southwards, so dy_px = −Δrow.)

Perspectives: an oblique map's view (azimuth θ, the compass bearing of the viewing direction,
elevation φ) is read from its file name stem (``az045_el45.tif``) unless given. On the map, a
point h above the ground shows at (x, y) + h·cot φ·(sin θ, cos θ), so whatever stands on the
ground leans along d = (sin θ, cos θ) and hides the ground behind it.

Modules: ``offsets`` (the result record and the measurement over a map pair), ``rasters``
(reading the maps and pairing their grids), ``visibility`` (which ground a view sees),
``correlation`` (one window: masked NCC and the sub-pixel fit), ``cli`` (``pipeline25d evaluate``).
"""
