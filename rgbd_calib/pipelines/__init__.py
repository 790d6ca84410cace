"""The use cases, the only place where the stages meet: :mod:`.calibrate`, :mod:`.refine`,
:mod:`.check` and :mod:`.posegraph` (the thesis CSV path). Each calls the layers below, one
call per stage; a pipeline never imports another.
"""
