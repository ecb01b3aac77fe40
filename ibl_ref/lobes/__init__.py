"""The lobe papers: analytic BRDFs, Kautz & McCool (2000) lobe fits and prefiltered maps, Meunier et al. (2009) cosine-lobe algebra."""
