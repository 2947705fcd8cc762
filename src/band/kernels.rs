//! Small dense kernels on column-major slices for the block-band operations.
