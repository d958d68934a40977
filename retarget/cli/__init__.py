"""The retargeter's commands: ``otr retarget`` (batches, local workers, Ray), ``otr demo``,
``otr score``, ``otr variants``, ``otr view`` and ``otr kernels``; imported only when their
command runs (``otr_gym.cli``)."""
