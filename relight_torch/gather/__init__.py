"""Clustered gather samples (the clustered-gather paper's equations 2 and 3): one indirect bounce relit from
clustered hemisphere gathers of clustered view samples."""
