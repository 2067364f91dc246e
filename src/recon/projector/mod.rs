//! Ray-driven forward projectors and their exact adjoints, for every canonical geometry.
