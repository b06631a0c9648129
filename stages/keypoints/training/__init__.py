"""Training of the keypoint network and its typing perceptron (paper §3.1, Appendix B).

The commands are :mod:`pipeline.train` (``polyvec-train``).

Usage::

    polyvec-train                                   # conf/train_app.yaml: train + keypoints + prep
    polyvec-train train.steps=2000 train.out_dir=runs/small train.network.level_channels=[8,16,32,64]

What it does, per step: a batch of crops of procedural drawings (stages/keypoints/training/generator.py,
generated on the fly by DataLoader workers, each drawing a pure function of (seed, worker, index);
with ``train.vector_prob`` > 0 that share of the drawings are human strokes of ``train.vector``, restyled
each time), prep's contrast normalisation and narrow band, the authors' network-input normalisation, Gaussian
targets (σ = ``sigma``), random flips / quarter turns, the masked asymmetric loss of Eq. 1, Adam with
cosine annealing. Crops grow in size during training (``crop_schedule``; the authors train on
80×80 crops of growing-resolution images). Every ``checkpoint_every`` steps ``last.pt`` is written
atomically (model, optimiser, scheduler, step); re-running the same command resumes from it. Every
``val.every`` steps the detector is scored on a fixed set of generated drawings (one-to-one F1
within 5 px and classification accuracy). At the end ``keypoints.pt`` (fp16 weights + network
config + training record) is exported: copy it to stages/keypoints/weights/ to ship it.

The training loop needs only torch, numpy, scipy, scikit-image and numba (and rich if present), so
it also runs where Hydra is not installed: ``python -m pipeline.train --plain conf_dir [key=value…]``.

``python -m pipeline.train --class-branch conf_dir train.init_weights=… [key=value…]`` re-trains only
the class branch on a frozen detector (:func:`~stages.keypoints.training.loop.train_class_branch`, settings ``train.class_branch``):
detection stays exactly as it was, and the run takes minutes on one CPU thread because the trunk runs
once per drawing and the branch trains on cached feature patches around the keypoints.

``python -m pipeline.train --type-classifier conf_dir [key=value…]`` trains the keypoint typing
perceptron of :mod:`stages.keypoints.valence` (settings ``train.type_classifier``) on the detected
keypoints of generated drawings run through the real prep and keypoints stages.
"""

# The entry points load lazily (PEP 562, :mod:`stages.lazy`): the configs import ``training.config`` at
# every start-up, and the training modules import torch (about 1.5 s), which a plain vectorisation never needs.
from stages.lazy import lazy_names

__getattr__, __dir__ = lazy_names(__name__, {
    "stages.keypoints.training.data": ("category_split", "draw_vector", "prepare_sample", "render_vector",
                                       "stroke_count_cdf", "validation_set", "vector_pool", "vector_samples",
                                       "vector_split"),
    "stages.keypoints.training.loop": ("train",),
    "stages.keypoints.training.validation": ("evaluate",),
    "stages.keypoints.training.checkpoints": ("export_weights",),
    "stages.keypoints.training.class_branch": ("train_class_branch",),
    "stages.keypoints.training.type_classifier": ("fit_type_classifier", "train_type_classifier",
                                                  "type_classifier_data"),
})
