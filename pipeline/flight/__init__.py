"""Flight folders in: ``flight.yaml`` schema, folder reader, navigation, EXIF/XMP, camera,
dropouts."""
