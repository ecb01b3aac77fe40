"""Environment maps: geometry and conventions, seam-aware sampling, resampling, file formats."""
