//! Blob storage for uploaded datasets and results (local files; ids, never client strings, name paths).
