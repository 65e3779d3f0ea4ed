"""Numerical tolerances, in one place (colours are sRGB in [0, 1]).

Each constant names the geometric test it guards; kernels and wrappers import
them from here rather than scattering literals.
"""

#: A colour closer than this to a palette vertex takes that vertex's weight alone.
VERTEX_TOL = 1e-10

#: A colour closer than this to an edge takes linear weights of its two ends.
EDGE_TOL = 1e-10

#: A colour closer than this to a face plane (and inside the face) takes
#: barycentric weights of the face, reproducing it to within this distance;
#: farther away the mean-vector form of MVC in ``kernels/mean_value.py`` stays accurate.
FACE_TOL = 1e-10

#: A colour whose signed distance to every face plane is below this is inside.
INSIDE_TOL = 1e-12

#: The edge-collapse LPs of hull simplification (``kernels.collapse_lp.collapse_points``):
#: a point counts as outside a facet plane when n . v + offset >= -LP_FEASIBILITY_TOL,
#: a basis as optimal when its dual weights are >= -LP_OPTIMALITY_TOL, and as singular
#: when a pivot (for three variables, its determinant) is below LP_PIVOT_TOL (its rows
#: are unit normals).
LP_FEASIBILITY_TOL = 1e-9
LP_OPTIMALITY_TOL = 1e-12
LP_PIVOT_TOL = 1e-12

#: Relative size of a singular value under which a colour set is taken to have
#: lost a dimension (collinear greys, coplanar colours).
RANK_TOL = 1e-9

#: Invariants every weight vector satisfies (the tests check them).
WEIGHT_MIN = -1e-7
WEIGHT_SUM_TOL = 1e-6

#: HCL chroma (CIE L*a*b* units) under which a colour counts as achromatic: its
#: hue neither steers a harmony fit nor moves. Turning the hue of such a colour
#: moves it by at most 2 * C, under one just-noticeable difference (about 2.3).
ACHROMATIC_CHROMA = 1.0

#: A colour whose sRGB channels lie this far outside [0, 1] is out of gamut.
GAMUT_TOL = 1e-9
