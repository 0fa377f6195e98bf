// Volume upload, with progress: a 500 MB DICOM zip needs a bar.

import { request } from './api.js';

// Resolves with the new volume's JSON; onProgress(fraction, phase) where
// phase is 'sending' while bytes go out and 'reading' once they are all sent
// and the server parses the series (which can take a while for DICOM).
export function uploadVolume( file, onProgress = () => {} ) {
	const form = new FormData();
	form.append( 'file', file, file.name );
	return request( 'POST', '/api/volumes', form, { onProgress } );
}

// The server decides what it can read; this only catches the obvious mistake
// (a PDF, a folder) before sending bytes.
export const ACCEPT = [ '.zip', '.nii', '.nii.gz', '.nrrd', '.mha' ];

export function looksLikeVolume( name ) {
	const lower = name.toLowerCase();
	return ACCEPT.some( ( ext ) => lower.endsWith( ext ) );
}
