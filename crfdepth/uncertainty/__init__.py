"""The CRF's uncertainty: the posterior variance and the predictive std (docs/design.md section 5)."""
