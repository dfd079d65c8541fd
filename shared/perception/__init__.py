"""Edge (MEC) perception algorithms: synchronisation, preprocessing, fusion; no bus inside."""
