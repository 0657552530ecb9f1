//! G-code interpreter (Type A lathe dialect). Built in src/interp/.
