-- Rows whose file was found missing by the start-up sweep (a crash between a row and its rename, or a file
-- removed by hand). The row stays, so its id answers "gone" rather than "never existed".

CREATE TABLE missing_blobs (
    kind         TEXT NOT NULL CHECK (kind IN ('series', 'dataset')),
    id           TEXT NOT NULL,
    detected_us  INTEGER NOT NULL,
    PRIMARY KEY (kind, id)
);
