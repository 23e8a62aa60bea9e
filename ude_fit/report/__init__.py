"""Reports: the markdown pages and the figures written from a fit's, a loop's and a
pipeline's results."""
