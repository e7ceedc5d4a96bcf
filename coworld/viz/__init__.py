"""Looking inside the models and the data (``coworld viz``).

* :mod:`coworld.viz.predictions`: open-loop video prediction, truth / model / error (the paper's Figure 5; the
  strip every training evaluation writes to TensorBoard is :mod:`coworld.training.openloop`'s);
* :mod:`coworld.viz.latents`: t-SNE of posterior latents by domain and encoder, with a domain classifier's
  accuracy and the matched-latent distance (Figure 6);
* :mod:`coworld.viz.dataset`: frame grids, episode videos and return histograms of a dataset;
* :mod:`coworld.viz.media` and :mod:`coworld.viz.runs`: PNG / GIF / MP4 files, a run's models.

t-SNE and the plots need the ``viz`` extra (scikit-learn, matplotlib).
"""
