//! Service configuration: file plus `CTRECON_*` environment variables.
