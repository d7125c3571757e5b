"""The parts of ``benchmarks/accuracy.py``, each documented in its module:

- :mod:`.protocols`: which frames, inputs and targets each protocol (a, a22, b, bu, c, s, q,
  q22) builds;
- :mod:`.methods`: the methods (nearest fill, IP-Basic, inpainting, the CRFs) and how each
  is run on a frame;
- :mod:`.fits`: where each protocol's ``learned`` weights come from, and the recipe's fits;
- :mod:`.evaluation`: the metrics, uncertainty and speed per method, and the sub-sampling
  study;
- :mod:`.report`: the tables, verdicts and plots.
"""
