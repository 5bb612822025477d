"""The data that ships inside d2f: installed as the package ``d2f_core.assets``.

``pyproject.toml`` maps this folder into the package, so a wheel carries ``weights/`` and
``samples/`` (and this folder's README with their sources and licences). Code finds them with
:mod:`d2f_core.bundled`. There is no code here.
"""
