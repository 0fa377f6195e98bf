// Volume upload, with progress: a 500 MB DICOM zip needs a bar.

import { request } from './api.js';

// Resolves with the new volume's JSON; onProgress(fraction, phase) where
// phase is 'sending' while bytes go out and 'reading' once they are all sent
// and the server parses the series (which can take a while for DICOM).
// `files`: one file, or several that make one scan (the slices of a series, a
// MetaImage header with its data file): the server gathers them into one folder.
// `fields`: e.g. { series: uid } to read one series of several.
export function uploadVolume( files, onProgress = () => {}, fields = {} ) {
	const form = new FormData();
	for ( const file of [].concat( files ) ) form.append( 'file', file, file.name );
	for ( const [ name, value ] of Object.entries( fields ) ) form.append( name, value );
	return request( 'POST', '/api/volumes', form, { onProgress } );
}

// Files that hold a whole scan by themselves: several picked at once are
// several scans, each sent alone. Anything else (.dcm slices, DICOM files
// without an extension, .mhd with its .raw or .zraw) is a part of one scan.
export const WHOLE = [ '.zip', '.nii', '.nii.gz', '.nrrd', '.mha' ];

// What no scanner writes: refused here before any byte is sent.
const NOT_SCANS = [ '.pdf', '.doc', '.docx', '.txt', '.rtf', '.jpg', '.jpeg', '.png', '.gif',
	'.html', '.htm', '.xls', '.xlsx', '.csv', '.json', '.xml', '.mp4', '.mov', '.exe' ];

const endsWith = ( name, list ) => list.some( ( ext ) => name.toLowerCase().endsWith( ext ) );

// Junk a desktop adds to folders (.DS_Store, Thumbs.db, macOS "._" twins).
function isJunk( name ) {
	return name.startsWith( '.' ) || name.toLowerCase() === 'thumbs.db' || name.toLowerCase() === 'desktop.ini';
}

export function looksLikeVolume( name ) {
	return ! endsWith( name, NOT_SCANS ) && ! isJunk( name );
}

// The uploads a set of files makes: each whole-scan file alone, the rest
// together as one. `refused` lists the names left out as not scans.
export function groupUploads( files ) {
	const kept = files.filter( ( f ) => looksLikeVolume( f.name ) );
	const refused = files.filter( ( f ) => ! isJunk( f.name ) && ! looksLikeVolume( f.name ) ).map( ( f ) => f.name );
	const parts = kept.filter( ( f ) => ! endsWith( f.name, WHOLE ) );
	const groups = kept.filter( ( f ) => endsWith( f.name, WHOLE ) ).map( ( f ) => [ f ] );
	if ( parts.length ) groups.push( parts );
	return { groups, refused };
}

// How the page names an upload of one or several files.
export function uploadLabel( files, folder = '' ) {
	if ( files.length === 1 ) return files[ 0 ].name;
	return `${folder || files[ 0 ].name + ' and others'} (${files.length} files)`;
}

// Every file under the dropped items, folders walked (as the desktop shows them).
// The entries must be taken during the drop event, so this is called there.
export function droppedFiles( dataTransfer ) {
	const entries = [ ...( dataTransfer?.items || [] ) ]
		.map( ( item ) => item.webkitGetAsEntry?.() )
		.filter( Boolean );
	if ( ! entries.length ) return Promise.resolve( { files: [ ...( dataTransfer?.files || [] ) ], folder: '' } );
	const folder = entries.length === 1 && entries[ 0 ].isDirectory ? entries[ 0 ].name : '';
	return Promise.all( entries.map( walk ) ).then( ( lists ) => ( { files: lists.flat(), folder } ) );
}

function walk( entry ) {
	if ( entry.isFile ) return new Promise( ( resolve, reject ) => entry.file( ( f ) => resolve( [ f ] ), reject ) );
	const reader = entry.createReader();
	const all = [];
	// readEntries hands out a folder in batches (100 in Chromium) until an empty one.
	const next = () => new Promise( ( resolve, reject ) => reader.readEntries( resolve, reject ) )
		.then( ( batch ) => {
			if ( ! batch.length ) return Promise.all( all.map( walk ) ).then( ( lists ) => lists.flat() );
			all.push( ...batch );
			return next();
		} );
	return next();
}
