"""Everything that turns MMAUD(-like) recordings into batches: data model, formats, simulator, teacher, features."""
