//! Task families, each in its folder: the private evaluators first written for it and the scripted experts of its
//! tasks. A family imports the shared machinery (`judge`, `expert`) and nothing of another family; the registry is
//! the one place that names them all.
pub mod adapted;
pub mod libero;
pub mod long_horizon;
pub mod perception;
pub mod vlabench;
