"""``ci``: Tamstorf and Jensen 1997 -- tone-operator confidence intervals, bootstrap bias, chi-square normality.

* :mod:`.method` -- :class:`CIMethod` and its stopping rule;
* :mod:`.tone` -- the tone operators;
* :mod:`.analysis` -- samples grouped by pixel, the bootstrap bias of the stopping rule, the chi-square test.
"""

from .method import CIMethod, StoppingRule

__all__ = ["CIMethod", "StoppingRule"]
