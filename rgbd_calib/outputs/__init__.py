"""What a run writes: the staged, atomic writer (:mod:`.writer`), the exports (:mod:`.exports`),
the printable board (:mod:`.printing`) and the report (:mod:`.report`: report.json and
report.html). Reads the pipelines' result types; nothing below imports it.
"""
