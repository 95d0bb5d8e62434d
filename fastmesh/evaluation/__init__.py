"""Measures of a result: distances and edge scores (``metrics``), the quality report every result carries
(``quality``), the ladder of simple shapes (``primitives``) and evaluation runs over a data set (``eval``)."""
