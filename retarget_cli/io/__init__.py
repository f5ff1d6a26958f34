"""File formats: every read and write of the pipeline lives here."""
