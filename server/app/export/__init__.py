"""What leaves the database: ``tables`` (the CSV export and its data dictionary) and ``minari``
(the demonstrations as Minari datasets)."""
