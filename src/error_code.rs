//! The one catalogue of stable API error codes.
