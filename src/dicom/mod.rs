//! DICOM: the only module that imports dicom-rs — reading CT series and writing derived results.
