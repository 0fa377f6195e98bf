"""PACS test data: DICOM series, SEG and RT-STRUCT objects built for the tests."""
