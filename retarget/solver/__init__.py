"""The OTRetarget method (``docs/method.md``): surface probes, optimal-transport correspondences,
interaction residuals, style and stance targets, the problem's data, its rows, the QP (ProxQP)
and the trust-region SQP over robot and object poses, the ballistic pass and object
substitution."""
