"""pipeline25d: orthorectified multi-perspective 2.5D maps from 3D city models.

Importing the package is cheap: no GL context, dataset or mesh is opened here, so
Snakemake can import it at parse time on every cluster job.
"""

__version__ = "0.1.0"
