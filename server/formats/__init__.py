"""The field's formats: COLMAP sparse models (``pycolmap``) and kapture datasets
(``kapture``) imported as mapping runs and written from maps. The libraries are the
``formats`` extra and are imported only where they are used."""
