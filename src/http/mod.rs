//! The HTTP layer: the only module that imports axum (router, extractors, errors, routes).
