"""Reading and writing: point cloud files (:mod:`~pfnet.io.clouds`) and their formats
(:mod:`~pfnet.io.formats`), writes that never leave half a file and the checks on every
output (:mod:`~pfnet.io.files`), paths whatever bytes they hold (:mod:`~pfnet.io.paths`),
the folder locks that keep two runs apart (:mod:`~pfnet.io.locks`), and the paper's colours
that pictures and coloured clouds share (:mod:`~pfnet.io.palette`)."""
