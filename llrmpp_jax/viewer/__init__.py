"""Interactive viewer: :mod:`.render` (one view, no browser), :mod:`.scene` (what is shown),
:mod:`.server` (the viser page, ``llrmpp view``)."""
