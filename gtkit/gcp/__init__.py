"""Marking GCPs in gtkit (issue 46): a surveyor's GCP coordinates in (:mod:`.points`), their
predicted positions in every photo of the reference block (:mod:`.predict`), the clicks'
triangulation, residuals and quick refit (:mod:`.marking`), and ``gcp_list.txt`` out
(:func:`gtkit.io.odm.write_gcp_list`). The annotator's GCP page is a view over these; nothing here
imports Qt."""
