"""The posterior (paper Eqs. 8-12): the similarity term, the elastic parameters and their
priors, the log-density; and a problem assembled from a config.
"""
