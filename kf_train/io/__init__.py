"""Floor 3, input and output: the exact bulk CSV codec."""  # noqa: A005 (see below)

# The name shadows the standard library's io only for code run with kf_train/ itself on
# sys.path, which nothing does: every import of this package is absolute (kf_train.io).
